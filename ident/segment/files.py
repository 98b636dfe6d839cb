"""Segment a recording file of any length window by window (bounded memory).

:func:`segment_file` walks the file with :func:`ident.io.iter_recording`
(windows of ``window_s`` that overlap by ``overlap_s``) and segments each window.
A transient is kept by the window that *owns* its ``t_step``: window ``k`` reads
``[k w - o, (k + 1) w)`` and owns ``[k w - o/2, (k + 1) w - o/2)``, so every
step is found once, with at least ``o/2`` of signal on either side (more than
the longest fit window plus the level windows, for the default ``o = 30 s``).
A recording no longer than one window is read whole, as
:func:`segment_transients` of :func:`ident.io.read_recording` would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..description import Mill
from ..errors import RecordingError
from ..io.readers import iter_recording, read_recording, recording_span
from ..io.recording import QualityIssue
from .transients import Segment, segment_transients

__all__ = ["FileSegments", "segment_file"]


@dataclass(frozen=True)
class FileSegments:
    """The transients of a recording file and what reading it found.

    Attributes
    ----------
    segments : tuple of Segment
        In time order (seconds from the recording's start).
    issues : tuple of QualityIssue
        The quality findings of every window read.
    channels : tuple of str
        The channels read.
    t0_ns : int
        The recording's absolute start, ns since the Unix epoch.
    duration_s : float
        Seconds from its start to its last sample.
    windows : int
        How many windows were read.
    """

    segments: tuple[Segment, ...]
    issues: tuple[QualityIssue, ...]
    channels: tuple[str, ...]
    t0_ns: int
    duration_s: float
    windows: int


def segment_file(path: str | Path, mill: Mill, *, window_s: float = 600.0,
                 overlap_s: float = 30.0, **options: Any) -> FileSegments:
    """Find every bite and release in a recording file, reading it window by window.

    Parameters
    ----------
    path : str or Path
        ``.mcap`` or ``.csv`` recording.
    mill : Mill
    window_s : float
        Seconds read at a time (memory: about 100 MB per 10 minutes of 8 torque
        channels at 2 kHz plus 4 accelerometers at 10 kHz).
    overlap_s : float
        Overlap of consecutive windows, s; at least twice the longest transient
        window plus the level windows (default 30 s).
    **options
        Passed to :func:`segment_transients` (``pre_s``, ``min_step``, ...).

    Returns
    -------
    FileSegments

    Raises
    ------
    RecordingError
        As :func:`ident.io.read_recording` and :func:`segment_transients`.
    """
    if not (window_s > 0 and 0 <= overlap_s <= window_s / 2):
        raise RecordingError(f"expected window_s > 0 and 0 <= overlap_s <= window_s / 2. Got "
                             f"window_s={window_s!r}, overlap_s={overlap_s!r}", path=str(path))
    try:
        single = recording_span(path) < window_s - overlap_s
    except RecordingError:  # nothing to walk: the whole read says what is wrong
        single = True
    segments: list[Segment] = []
    issues: list[QualityIssue] = []
    channels: tuple[str, ...] = ()
    t0_ns, duration, n = 0, 0.0, 0
    parts = iter((read_recording(path, mill, warn=False),)) if single else \
        iter_recording(path, mill, window_s=window_s, overlap_s=overlap_s, warn=False)
    pending: tuple[int, tuple[Segment, ...]] | None = None

    def own(k: int, found: tuple[Segment, ...], last: bool) -> None:
        lo = -math.inf if k == 0 else k * window_s - overlap_s / 2
        hi = math.inf if last else (k + 1) * window_s - overlap_s / 2
        segments.extend(s for s in found if lo <= s.t_step < hi)

    for rec in parts:
        n += 1
        t0_ns, duration = rec.t0_ns, max(duration, rec.duration)
        channels = channels or rec.channels
        issues.extend(rec.issues)
        start = float(next(iter(rec.frames.values())).index[0])
        k = 0 if single else round((start + overlap_s) / window_s)
        found = segment_transients(rec, mill, **options)
        if pending is not None:
            own(*pending, last=False)
        pending = (k, found)
    if pending is not None:
        own(*pending, last=True)
    segments.sort(key=lambda s: s.t_step)
    return FileSegments(segments=tuple(segments), issues=tuple(issues), channels=channels,
                        t0_ns=t0_ns, duration_s=duration, windows=n)
