"""What processing one recording produces: plain dicts in the shapes of cli.md.

:class:`RecordingOutcome` is the only thing a worker sends back to the campaign's
parent process, and the only thing the store writes; it holds no ndarray and no
object of the upstream stages, so the store and the report depend on the JSON
contracts (``../shared/spec/cli.md``) alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, Mapping

import numpy as np

__all__ = ["RecordingOutcome", "Stage", "jsonable"]

#: Stages of processing one recording, in order.
Stage = Literal["read", "segment", "taf", "fit", "diagnose"]


def jsonable(obj: Any) -> Any:
    """Plain JSON values: numpy scalars and arrays unpacked, NaN and inf as None."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


@dataclass(frozen=True)
class RecordingOutcome:
    """The result of processing one recording, successful or not.

    Attributes
    ----------
    status : {'done', 'failed'}
    error : str or None
        Why it failed, one line naming the stage, file, channel or key.
    error_kind : str or None
        The exception's class name (``RecordingError``, ``FitError``, ...).
    stage : str or None
        The stage that failed (``read``, ``segment``, ``taf``, ``fit``, ``diagnose``).
    recording : dict
        ``recording_id``, ``metadata`` (dict), ``t0_ns`` (ns since the Unix epoch),
        ``duration_s``; empty when the file could not be read.
    segments : tuple of dict
        cli.md ``segment`` entries (``t_start, t_step, t_end, kind, static_torque, step``).
    taf : tuple of dict
        Measured TAF per bite and torque channel: ``transient_idx, element, channel,
        static_torque, peak_torque, taf`` (N*m reduced to the motor shaft).
    fit : dict or None
        cli.md ``fit`` JSON over all transients of the recording.
    transient_fits : tuple of dict
        cli.md ``fit`` JSON per transient, each with an extra ``transient_idx``.
    diagnosis : dict or None
        cli.md ``diagnose`` JSON.
    quality : tuple of dict
        Data-quality findings (``QualityIssue.to_dict()`` plus ``stage``), including
        warnings the stages raised.
    versions : dict
        ``ident`` and library versions of the worker.
    started_at : float
        POSIX time the worker started, s.
    elapsed_s : float
        Wall time spent in the worker, s.
    worker : str
        ``host:pid`` of the worker.
    """

    status: Literal["done", "failed"]
    error: str | None = None
    error_kind: str | None = None
    stage: str | None = None
    recording: Mapping[str, Any] = field(default_factory=dict)
    segments: tuple[Mapping[str, Any], ...] = ()
    taf: tuple[Mapping[str, Any], ...] = ()
    fit: Mapping[str, Any] | None = None
    transient_fits: tuple[Mapping[str, Any], ...] = ()
    diagnosis: Mapping[str, Any] | None = None
    quality: tuple[Mapping[str, Any], ...] = ()
    versions: Mapping[str, str] = field(default_factory=dict)
    started_at: float = 0.0
    elapsed_s: float = 0.0
    worker: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "done"
