"""Model discrepancy: find what the model is missing, name it, add it, show the gap shrink.

Stages, in the order data passes through them::

    recording ─► windows (bites, releases, by bar)          windows.py
              ─► mill file's model fitted per fold            engine.py
              ─► held-out residuals: time, phase, frequency   residuals.py
              ─► candidates ranked by signature               signatures.py
              ─► leading candidates added, refitted, judged   workflow.py
                 on held-out bars ─► name or null
              ─► plots beside the JSON                        plots.py

The effect vocabulary is ``spec/effects.md``; the effects themselves are model
terms in :mod:`ident.model.effects`.  :mod:`.synthetic` hides effects in
simulated recordings to test the workflow.
"""

from .residuals import ResidualReport, analyse_residuals
from .signatures import CandidateScore
from .synthetic import CONTROLS, STRENGTHS, HiddenCase, hidden_effect_case
from .windows import Window, as_windows, windows_from_recording
from .workflow import DecisionRule, DiscrepancyResult, Refit, discrepancy

__all__ = ["discrepancy", "DiscrepancyResult", "DecisionRule", "Refit", "CandidateScore",
           "ResidualReport", "analyse_residuals", "Window", "windows_from_recording",
           "as_windows", "hidden_effect_case", "HiddenCase", "CONTROLS", "STRENGTHS"]
