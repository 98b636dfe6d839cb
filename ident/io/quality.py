"""Data-quality checks of recordings (``../shared/spec/telemetry.md``, "Bad input").

The readers call these while they assemble a recording; every finding is a
:class:`~ident.io.recording.QualityIssue` naming the file, the channel(s) and the time
(seconds from the recording's start).  What is fatal and what is a warning:

============================  ==========================================================
kind                          handling
============================  ==========================================================
``unit_mismatch``             fatal: a recorded unit other than the mill file's (or ``raw``),
                              or an MCAP device whose units change between its blocks
``rate_mismatch``             fatal: a device's declared rate disagrees with its block
                              timestamps by more than 0.5 %, or a CSV file whose time
                              steps are not one rate
``missing_channel``           fatal when the caller asked for the channel (``channels=``);
                              otherwise a warning when other channels of the same
                              quantity are present (a dead sensor), and nothing when the
                              whole quantity is absent (a torque-only recording is normal)
``unreadable``                fatal: not an MCAP/CSV file, or nothing in it is readable
``truncated``                 warning: the file breaks off (or is corrupt with no index to
                              skip the bad part); everything before is read, ``t_start`` is
                              the end of the last good block
``corrupt``                   warning: an indexed MCAP chunk, or one message, cannot be
                              decoded; it is skipped (its time range is a gap) and the
                              rest is read
``dropout``                   warning: missing samples (an MCAP block that never came, a
                              gap in a CSV time column); kept as NaN rows on the uniform
                              time grid, never interpolated
``nan_run``                   warning: NaN samples inside received data
``clipped``                   warning: a run of >= 4 identical samples at the channel's
                              extreme (saturation), or at the 16-bit full scale of a
                              ``raw`` channel
``flat``                      warning: a channel that never changes (dead sensor)
``non_monotonic``             fatal: time that steps back or repeats (a CSV row whose time
                              is not after the row before; an MCAP block of a device whose
                              first sample is not after the last sample of the block
                              before it in time; blocks may arrive in any order): the
                              order of samples is not guessed (telemetry.md).  Warning:
                              CSV rows without a valid time (dropped), CSV time steps off
                              the rate's grid by more than a quarter sample, an MCAP block
                              starting less than a sample after the one before (its first
                              sample shares the grid point of that block's last; the block
                              read last wins)
``time_jump``                 fatal: a device's time stamps jump by more than
                              :data:`MAX_DROPOUT_S` (an hour): a wrong time stamp, not a
                              dropout (its NaN rows would fill memory)
``timestamp_mismatch``        warning: an MCAP ``log_time`` disagreeing with the block's
                              ``t0_ns`` by more than a sample (``t0_ns`` is used)
``unknown_channel``           warning: a channel the mill file does not map; ignored
``unscaled``                  warning: without a mill file, a channel whose unit ident
                              cannot bring to SI is kept as recorded
============================  ==========================================================

Dropouts are represented as NaN rows: every device's frame has a uniform index
``t0 + k / rate``, so spectra and windows need no resampling, and the gap is visible
both in the data and in the issue list.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import DataQualityWarning, RecordingError
from .recording import QualityIssue

__all__ = ["IssueLog", "find_runs", "scan_channel", "gap_issues", "RATE_TOLERANCE",
           "CLIP_MIN_RUN", "MAX_ISSUES_PER_KIND", "MAX_DROPOUT_S"]

#: Relative disagreement between declared and timestamp rate that is fatal.
RATE_TOLERANCE = 0.005
#: Shortest run of identical extreme samples reported as clipping.
CLIP_MIN_RUN = 4
#: Findings of one kind on one channel listed one by one; the rest are summarised.
MAX_ISSUES_PER_KIND = 10
#: Longest dropout, s: a gap in a device's time stamps beyond this is taken for a wrong
#: time stamp (a corrupt or cut row or block), not for a telemetry dropout to fill with NaN.
MAX_DROPOUT_S = 3600.0

_INT16_FULL_SCALE = 32767.0


@dataclass
class IssueLog:
    """Collects the findings of one read (a local object: no global state).

    Parameters
    ----------
    path : str
        The recording, named in every finding.
    """

    path: str
    issues: list[QualityIssue] = field(default_factory=list)
    _counts: dict[tuple[str, str | None], int] = field(default_factory=dict)
    _dropped: dict[tuple[str, str | None], int] = field(default_factory=dict)

    def add(self, kind: str, message: str, *, channel: str | None = None,
            t_start: float | None = None, t_end: float | None = None,
            device: str | None = None) -> None:
        """Record a non-fatal finding (at most :data:`MAX_ISSUES_PER_KIND` per kind and channel)."""
        key = (kind, channel)
        n = self._counts.get(key, 0)
        self._counts[key] = n + 1
        if n >= MAX_ISSUES_PER_KIND:
            self._dropped[key] = self._dropped.get(key, 0) + 1
            return
        self.issues.append(QualityIssue(kind=kind, message=message, path=self.path,
                                        channel=channel, t_start=t_start, t_end=t_end,
                                        device=device))

    def fatal(self, kind: str, message: str, *, channel: str | None = None,
              time: float | None = None, path: str | None = None) -> RecordingError:
        """Return the RecordingError of a fatal finding (the caller raises it).

        ``path`` names another file of the recording (a CSV sibling) instead of
        :attr:`path`.
        """
        return RecordingError(f"{kind.replace('_', ' ')}: {message}", path=path or self.path,
                              channel=channel, time=time)

    def finish(self, *, warn: bool) -> tuple[QualityIssue, ...]:
        """Add the summaries of capped kinds, emit warnings, and return the findings."""
        for (kind, channel), n in self._dropped.items():
            self.issues.append(QualityIssue(
                kind=kind, path=self.path, channel=channel,
                message=f"{n} more findings of this kind not listed one by one"))
        self._dropped.clear()
        if warn:
            for issue in self.issues:
                warnings.warn(str(issue), DataQualityWarning, stacklevel=4)
        return tuple(self.issues)


def find_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) indices of the runs of True in a 1-D boolean array."""
    m = np.asarray(mask, dtype=bool)
    if m.size == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    d = np.diff(m.view(np.int8))
    starts = np.flatnonzero(d == 1) + 1
    ends = np.flatnonzero(d == -1) + 1
    if m[0]:
        starts = np.concatenate(([0], starts))
    if m[-1]:
        ends = np.concatenate((ends, [m.size]))
    return starts.astype(np.int64), ends.astype(np.int64)


def gap_issues(log: IssueLog, device: str, channels: Sequence[str], rate_hz: float,
               offset_s: float, gaps: Sequence[tuple[int, int]],
               skip: Sequence[tuple[float, float]] = ()) -> None:
    """Report dropouts ``[i0, i1)`` (sample indices) of a device as ``dropout`` findings.

    Gaps overlapping a range of ``skip`` (times, s, already reported as ``corrupt``)
    are not reported twice.
    """
    names = ",".join(channels)
    for i0, i1 in gaps:
        t0 = offset_s + i0 / rate_hz
        t1 = offset_s + i1 / rate_hz
        if any(t0 <= b and a <= t1 for a, b in skip):
            continue
        log.add("dropout", f"device {device!r}: no samples for {t1 - t0:.4f} s ({i1 - i0} "
                f"samples at {rate_hz:g} Hz) from t={t0:.4f} s to t={t1:.4f} s; kept as NaN "
                "rows, not interpolated", channel=names, t_start=t0, t_end=t1, device=device)


def _quantum(x: np.ndarray) -> float:
    """Smallest step between distinct values in a sample of ``x`` (the quantisation)."""
    sample = x[:: max(1, x.size // 200_000)]
    sample = sample[np.isfinite(sample)]
    u = np.unique(sample)
    if u.size < 2:
        return 0.0
    return float(np.min(np.diff(u)))


def scan_channel(log: IssueLog, device: str, channel: str, x: np.ndarray, *, rate_hz: float,
                 offset_s: float, gap_mask: np.ndarray | None = None,
                 recorded: np.ndarray | None = None) -> None:
    """Look for NaN runs, clipping and a flat channel in one channel's samples.

    Parameters
    ----------
    log : IssueLog
    device, channel : str
    x : ndarray, shape (n,)
        Samples (any unit); NaN = missing.
    rate_hz : float
    offset_s : float
        Time of ``x[0]`` from the recording's start, s.
    gap_mask : ndarray of bool, optional
        True where a dropout (already reported) made the NaN.
    recorded : ndarray, optional
        Raw recorded values of a ``raw`` channel, checked against 16-bit full scale.
    """
    n = x.size
    if n == 0:
        return

    def t(i: int) -> float:
        return offset_s + i / rate_hz

    hi = float(np.max(x))  # NaN if any sample is NaN: one pass tells both
    lo = float(np.min(x))
    if np.isnan(hi) or np.isnan(lo):
        nan = np.isnan(x)
        own = nan & ~gap_mask if gap_mask is not None else nan
        starts, ends = find_runs(own)
        for s, e in zip(starts.tolist(), ends.tolist()):
            log.add("nan_run", f"{e - s} NaN samples ({(e - s) / rate_hz:.4f} s) from "
                    f"t={t(s):.4f} s to t={t(e):.4f} s; kept as NaN, not interpolated",
                    channel=channel, t_start=t(s), t_end=t(e), device=device)
        if nan.all():
            return
        hi = float(np.nanmax(x))
        lo = float(np.nanmin(x))
    if hi == lo:
        log.add("flat", f"every sample is {hi:g}: the sensor looks dead or disconnected",
                channel=channel, t_start=t(0), t_end=t(n), device=device)
        return
    candidates: list[tuple[np.ndarray, str]] = []
    bulk: tuple[float, float] | None = None
    for level, name in ((hi, "maximum"), (lo, "minimum")):
        at = np.flatnonzero(x == level)
        if at.size < CLIP_MIN_RUN:
            continue
        if bulk is None:  # only now worth the sort: median and quantisation step
            bulk = (float(np.nanmedian(x[:: max(1, n // 200_000)])), _quantum(x))
        med, q = bulk
        if abs(level - med) < 16 * q:  # an extreme only a few steps from the bulk: noise
            continue
        candidates.append((at, f"the channel's {name} {level:g}"))
    if recorded is not None:
        candidates.append((np.flatnonzero(np.abs(recorded) >= _INT16_FULL_SCALE),
                           "the 16-bit full scale (|raw| >= 32767)"))
    for at, what in candidates:
        if at.size < CLIP_MIN_RUN:
            continue
        brk = np.flatnonzero(np.diff(at) != 1)
        starts = at[np.concatenate(([0], brk + 1))]
        ends = at[np.concatenate((brk, [at.size - 1]))] + 1
        keep = (ends - starts) >= CLIP_MIN_RUN
        for s, e in zip(starts[keep].tolist(), ends[keep].tolist()):
            log.add("clipped", f"{e - s} consecutive samples stuck at {what} from t={t(s):.4f} s "
                    f"to t={t(e):.4f} s: the signal saturated", channel=channel,
                    t_start=t(s), t_end=t(e), device=device)


def gap_mask_of(n: int, gaps: Sequence[tuple[int, int]]) -> np.ndarray | None:
    """Boolean mask of the dropout samples of a device, or None without dropouts."""
    if not gaps:
        return None
    m = np.zeros(n, dtype=bool)
    for i0, i1 in gaps:
        m[i0:i1] = True
    return m
