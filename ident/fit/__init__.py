"""Identify gaps and smoothing parameters from transient windows (cli.md ``ident fit``).

Data flow::

    Recording + Segments ──► windows_from_recording ──► FitWindow(s)
                                                             │
    Mill ──► FitModel (driveline, load ramp, layout) ────────┤
                                                             ▼
             fit_gaps(mill, windows, method=Collocation(degree=3)) ──► FitResult
               1. linear baseline (gaps closed)        nrmse_linear
               2. starts (designed gaps, random)       which start won
               3. strategy: Collocation | SingleShooting, continuation on the smoothing width
               4. assess: sandwich covariance, unseen / untraversed gaps flagged,
                  residuals checked against the noise floor

Modules: :mod:`.windows` (data), :mod:`.model` (parameter layout), :mod:`.problem`
(problem and estimates), :mod:`.simulator` (RK4 window simulation with sensitivities),
:mod:`.collocation` and :mod:`.shooting` (strategies), :mod:`.uncertainty`,
:mod:`.result`, :mod:`.core` (``fit_gaps``, ``assess``), :mod:`.synthetic` (simulated
recordings of known gaps, for tests and benchmarks).  :func:`fit_recording`
(:mod:`.recording`) runs the two steps for one recording, as every command does.
"""

from .collocation import Collocation
from .core import Assessment, assess, fit_gaps
from .model import FitModel, build_fit_model
from .problem import Estimate, Problem, make_problem
from .recording import fit_recording
from .result import NOISE_RATIO_MAX, ElementFit, FitResult, SolverReport
from .shooting import SingleShooting
from .synthetic import SyntheticCase, random_gaps, synthetic_case
from .windows import FitWindow, reduced_torque_frame, windows_from_recording

__all__ = ["fit_gaps", "fit_recording", "assess", "Assessment", "FitResult", "ElementFit",
           "SolverReport", "NOISE_RATIO_MAX", "Collocation", "SingleShooting", "FitWindow",
           "windows_from_recording", "reduced_torque_frame", "FitModel", "build_fit_model",
           "Problem", "Estimate", "make_problem", "SyntheticCase", "synthetic_case",
           "random_gaps"]
