"""Wear diagnosis: simulated library, classifiers, the model artefact, bearings.

    mill file ──► library.simulate_library (a few worn elements, clearances, nuisance)
                      │ features (ident.features)
                      ▼
                  model.train_model ──► DiagnosticModel ──► save_model / load_model
                                              │
    recording features ──► model.diagnose_features ──► Diagnosis (+ explain)
                                              │  + the fit's identified gaps
                                              ▼
                              verdict.verdicts / diagnosis_json (one state per target)

``bearings`` gives the shaft-centre trajectory and the maximum radial load
against clearance (seed section 2.2, Fig. 8).
"""

from .bearings import RadialLoadCurve, maintenance_clearance, radial_load_curve, shaft_trajectory
from .estimators import GapRegressor, NoveltyDetector, WearClassifier
from .explain import describe_feature, explain_decision
from .library import (Library, LibraryRanges, LibrarySimulator, draw_sample, simulate_library,
                      simulate_sample)
from .model import (Diagnosis, DiagnosticModel, TargetDiagnosis, diagnose_features,
                    diagnose_recording, library_versions, load_model, model_cache_path,
                    save_model, train_model)
from .states import WearState, bearing_state, element_state
from .verdict import Verdict, diagnosis_json, fit_verdicts, state_probabilities, verdicts

__all__ = ["RadialLoadCurve", "maintenance_clearance", "radial_load_curve", "shaft_trajectory",
           "GapRegressor", "NoveltyDetector", "WearClassifier", "describe_feature",
           "explain_decision", "Library", "LibraryRanges", "LibrarySimulator", "draw_sample", "simulate_library",
           "simulate_sample", "Diagnosis", "DiagnosticModel", "TargetDiagnosis",
           "diagnose_features", "diagnose_recording", "library_versions", "load_model", "model_cache_path",
           "save_model", "train_model", "WearState", "bearing_state", "element_state",
           "Verdict", "verdicts", "fit_verdicts", "state_probabilities", "diagnosis_json"]
