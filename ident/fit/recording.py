"""The fit of one recording: the one place ``ident fit``, ``ident diagnose`` and the
campaign assemble the fit stage.

    Recording + Segments ──► require_channels ──► windows_from_recording ──► fit_gaps
"""

from __future__ import annotations

import warnings
from typing import Any, Callable, Mapping, Sequence

from ..description import Mill
from ..errors import ConvergenceWarning, FitError
from ..io.channels import require_channels
from .core import fit_gaps
from .result import FitResult
from .windows import FitWindow, windows_from_recording

__all__ = ["fit_recording"]


def fit_recording(rec: Any, mill: Mill, segments: Sequence[Any], *,
                  windows: Mapping[str, Any] | None = None,
                  on_windows: Callable[[Sequence[FitWindow]], None] | None = None,
                  **fit: Any) -> tuple[FitResult, list[FitWindow]]:
    """Fit the gaps of one recording around its load-step transients.

    Parameters
    ----------
    rec : Recording
        :func:`ident.io.read_recording` of the recording.
    mill : Mill
    segments : sequence of Segment
        Its transients (:func:`ident.segment.segment_transients`), the ones to fit.
    windows : mapping, optional
        Keywords of :func:`~ident.fit.windows_from_recording` (window lengths, kinds).
    on_windows : callable, optional
        Called with the windows before the (long) fit, e.g. to say what is fitted.
    **fit
        Keywords of :func:`~ident.fit.fit_gaps` (``family``, ``time_budget_s``, ``starts``,
        ``nuisance``, ``progress`` ...).  A :class:`~ident.errors.ConvergenceWarning` is not
        raised: the result says it (``converged``, each element's ``identified``).

    Returns
    -------
    result : FitResult
    windows : list of FitWindow
        The windows fitted, in time order.

    Raises
    ------
    RecordingError
        A torque channel of the mill file is missing (naming file and channel).
    FitError
        No transient, or no usable window around them.
    """
    require_channels(rec, mill, "fit")  # every torque channel: before the fit says less
    if not len(segments):
        raise FitError(f"{rec.path or 'the recording'}: no load-step transient found; a fit "
                       "needs at least one bite or release")
    ws = windows_from_recording(rec, mill, segments, **dict(windows or {}))
    if on_windows is not None:
        on_windows(ws)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        result = fit_gaps(mill, ws, **fit)
    return result, list(ws)
