"""ident: identification and diagnostics of rolling-mill drivelines.

The package is laid out by the stage of the data flow (seed: Krot, driveline
dynamics with non-smooth stiffness):

    mill file ──► io.load_mill ──► Mill (frozen description)
                                      │
    recording ──► io.read_recording ──► segment.segment_transients ──► Segment(s)
                                      │                                   │
                  model: laws, linear baseline, dynamics, simulate        │
                                      │                                   ▼
                                      └──────────────► fit.fit_gaps ──► FitResult
                                                          │
                       features ──► diagnose (classifier) ──► wear states
                                                          │
                       discrepancy (missing effects) ──► store / report (campaigns)

Everything inside is SI and reduced to the motor shaft (``ident.description``
states the sign conventions).
"""

from .description import (Bearing, Channel, Element, Load, Mass, Mill, Motor, Quantity,
                          StiffnessKind)
from .errors import (ConvergenceWarning, DataQualityWarning, FitError, IdentError,
                     MillFileError, RecordingError)
from .io.millfile import load_mill, parse_mill

__version__ = "0.1.0"

__all__ = ["Bearing", "Channel", "Element", "Load", "Mass", "Mill", "Motor", "Quantity",
           "StiffnessKind", "ConvergenceWarning", "DataQualityWarning", "FitError", "IdentError",
           "MillFileError", "RecordingError", "load_mill", "parse_mill", "__version__"]
