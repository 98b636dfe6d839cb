"""Wear features of load-step transients (seed sections 1.1, 2, 2.2).

    Recording + step times ──► transients.refine_transients ──► Transient(s)
        │                                                        │
        │     baseline.LinearReference (gaps closed, same step) ─┤
        ▼                                                        ▼
    spectral estimators (matrix pencil / LSQ / DFT) ─┐
    sweep: when each channel's flanks part and meet ─┼─► extract.transient_features
    rattle: the bearing shaft in its clearance ──────┘           │
                                                 extract.recording_features (one vector)
"""

from .baseline import LinearReference, UnitResponse
from .extract import (FeatureOptions, TransientFeatures, feature_summary, frequency_labels,
                      recording_features, transient_features)
from .rattle import rattle_features
from .spectral import MatrixPencil, ModalLSQ, WindowedDFT, benchmark_estimators
from .sweep import pair_differences, sweep_features
from .transients import Kind, Transient, find_steps, refine_transients, torque_signals

__all__ = ["LinearReference", "UnitResponse", "FeatureOptions", "TransientFeatures",
           "feature_summary", "frequency_labels", "recording_features", "transient_features",
           "rattle_features", "MatrixPencil", "ModalLSQ", "WindowedDFT", "benchmark_estimators",
           "pair_differences", "sweep_features", "Kind", "Transient", "find_steps",
           "refine_transients", "torque_signals"]
