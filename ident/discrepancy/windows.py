"""Transient windows grouped by bar: what the discrepancy workflow compares.

A :class:`Window` is one load step (a bite or a release) of measured torques
reduced to the motor shaft, resampled to a common rate, tagged with the bar it
belongs to so that cross-validation can hold whole bars out.
:func:`windows_from_recording` cuts them from a recording with
``ident.segment.segment_transients``; :func:`as_windows` also accepts windows
built elsewhere (anything with ``t, y, elements, t_step, kind`` and load levels,
such as ``ident.fit``'s ``FitWindow``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np
import pandas as pd

from ..description import Mill
from ..errors import FitError, RecordingError

__all__ = ["Window", "windows_from_recording", "windows_from_frame", "as_windows"]


@dataclass(frozen=True, eq=False)
class Window:
    """One load-step transient of measured reduced torques.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sample times, s from the recording's start, uniformly spaced.
    elements : tuple of str
        Element ids of the columns of ``y``.
    y : ndarray, shape (N, len(elements))
        Measured torques reduced to the motor shaft, N*m.
    t_step : float
        Half-height instant of the load step, s (segmenter's estimate).
    kind : {"bite", "release"}
    level_before, level_after : float
        Total rolling torque before and after the step, N*m reduced.
    bar : int
        Index of the bar (a bite and the release that follows share it).
    label : str
    rise : float
        Duration of the load ramp, s (segmenter's estimate; a start for fits).
    history : tuple of float or None
        For a bite after a release: ``(t_step, level_before, level_after, rise)`` of
        that release (s, N*m, N*m, s; segmenter's estimates), so that a model can
        run through the idle time in between (effects tied to the roll angle).
    """

    t: np.ndarray
    elements: tuple[str, ...]
    y: np.ndarray
    t_step: float
    kind: str
    level_before: float
    level_after: float
    bar: int
    label: str = ""
    rise: float = 0.02
    history: tuple | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        y = np.asarray(self.y, dtype=float)
        if y.ndim == 1:
            y = y[:, None]
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "elements", tuple(self.elements))
        if t.ndim != 1 or t.size < 16:
            raise FitError(f"Window {self.label!r}: t must be 1-D with at least 16 samples. "
                           f"Got shape {t.shape}.")
        if y.shape != (t.size, len(self.elements)):
            raise FitError(f"Window {self.label!r}: y must have shape ({t.size}, "
                           f"{len(self.elements)}). Got {y.shape}.")
        if not np.all(np.isfinite(y)):
            raise FitError(f"Window {self.label!r}: torques contain NaN or inf.")
        if self.kind not in ("bite", "release"):
            raise FitError(f"Window {self.label!r}: kind must be 'bite' or 'release'. "
                           f"Got {self.kind!r}.")

    @property
    def dt(self) -> float:
        """Sample interval, s."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def n_samples(self) -> int:
        return int(self.t.size)

    @property
    def static_torque(self) -> float:
        """Rolling level of the bar, N*m reduced."""
        return self.level_after if self.kind == "bite" else self.level_before

    def columns(self, elements: Sequence[str]) -> np.ndarray:
        """``y`` with columns in the order of ``elements``, shape (N, len(elements))."""
        return self.y[:, [self.elements.index(e) for e in elements]]

    def trimmed(self, n: int) -> "Window":
        """The first ``n`` samples."""
        return Window(t=self.t[:n], elements=self.elements, y=self.y[:n], t_step=self.t_step,
                      kind=self.kind, level_before=self.level_before,
                      level_after=self.level_after, bar=self.bar, label=self.label,
                      rise=self.rise, history=self.history)


def _element_frame(frame: pd.DataFrame, mill: Mill) -> pd.DataFrame:
    """Rename channel / ``tau:`` columns to element ids, keeping the mill's torque elements."""
    names = {c.name: c.element for c in mill.torque_channels()}
    cols = {}
    for col in frame.columns:
        c = str(col)
        eid = c[4:] if c.startswith("tau:") else names.get(c, c)
        if eid in mill.element_ids and eid not in cols.values():
            cols[col] = eid
    if not cols:
        raise FitError(f"no torque column matches an element of mill '{mill.name}'. Got "
                       f"{list(frame.columns)}; expected channel names {list(names)} or "
                       f"element ids.")
    return frame[list(cols)].rename(columns=cols)


def _resample(frame: pd.DataFrame, rate_hz: float) -> pd.DataFrame:
    """Anti-aliased integer decimation of a uniformly sampled frame to ``rate_hz``."""
    from scipy import signal

    t = frame.index.to_numpy(dtype=float)
    fs = 1.0 / float(np.median(np.diff(t[: min(t.size, 5000)])))
    q = int(round(fs / rate_hz))
    if q <= 1:
        return frame.astype(float)
    data = {}
    for c in frame.columns:
        x = frame[c].to_numpy(dtype=float)
        bad = ~np.isfinite(x)
        if bad.any():
            x = np.where(bad, np.interp(np.arange(x.size), np.flatnonzero(~bad), x[~bad]), x)
        y = signal.decimate(x, q, ftype="fir", zero_phase=True)
        if bad.any():
            y[np.add.reduceat(bad, np.arange(0, x.size, q))[: y.size] > 0] = np.nan
        data[c] = y
    return pd.DataFrame(data, index=pd.Index(t[::q][: len(y)], name="time_s"))


def windows_from_frame(frame: pd.DataFrame, mill: Mill, segments: Iterable[Any], *,
                       window_s: float = 0.45, pre_s: float = 0.05, rate_hz: float = 1000.0,
                       min_s: float = 0.3) -> tuple[Window, ...]:
    """Cut windows from reduced torques indexed by ``time_s`` around segmented steps.

    Parameters
    ----------
    frame : DataFrame
        Reduced torques, N*m; columns channel names, element ids or ``tau:ID``.
    mill : Mill
    segments : iterable
        Objects with ``t_start, t_step, kind, static_torque, step`` (s, N*m reduced),
        e.g. :class:`ident.segment.Segment`.
    window_s, pre_s : float
        Window length and lead before ``t_step``, s.
    rate_hz : float
        Resample to this rate (integer decimation, anti-aliased), Hz.
    min_s : float
        Shortest window kept, s (a window stops before the next step).

    Returns
    -------
    tuple of Window
        In time order, all of one length (the shortest kept); a bite starts a new bar.

    Raises
    ------
    FitError
        No usable window.
    """
    frame = _resample(_element_frame(frame, mill), rate_hz)
    t_all = frame.index.to_numpy(dtype=float)
    segs = sorted(segments, key=lambda s: s.t_step)
    out: list[Window] = []
    bar = -1
    for i, s in enumerate(segs):
        if s.kind == "bite" or bar < 0:
            bar += 1
        if not (math.isfinite(s.static_torque) and math.isfinite(s.step)):
            continue
        t0 = s.t_step - pre_s
        t1 = t0 + window_s
        if i + 1 < len(segs):
            t1 = min(t1, segs[i + 1].t_step - 0.06)
        m = (t_all >= t0 - 1e-9) & (t_all < t1 - 1e-9)
        if t1 - t0 < min_s or m.sum() < 16 or t0 < t_all[0]:
            continue
        y = frame.to_numpy()[m]
        if not np.all(np.isfinite(y)):
            continue
        if s.kind == "bite":
            before, after = s.static_torque - s.step, s.static_torque
        else:
            before, after = s.static_torque, s.static_torque + s.step
        history = None
        # the segmenter's 10-90 % time; a raised cosine of duration T rises 10-90 % in 0.59 T
        rise_s = getattr(s, "rise_s", math.nan)
        rise = (min(max(rise_s / 0.59, 0.004), 0.1) if math.isfinite(rise_s) and rise_s > 0
                else 0.02)
        prev = segs[i - 1] if i > 0 else None
        if (s.kind == "bite" and prev is not None and prev.kind == "release"
                and math.isfinite(prev.static_torque) and math.isfinite(prev.step)):
            prev_rise = getattr(prev, "rise_s", math.nan)
            prev_rise = prev_rise / 0.59 if math.isfinite(prev_rise) and prev_rise > 0 else 0.02
            history = (float(prev.t_step), float(prev.static_torque),
                       float(prev.static_torque + prev.step),
                       float(min(max(prev_rise, 0.004), 0.1)))
        out.append(Window(t=t_all[m], elements=tuple(frame.columns), y=y, t_step=float(s.t_step),
                          kind=s.kind, level_before=float(before), level_after=float(after),
                          bar=bar, label=f"{s.kind}@{s.t_step:.2f}s", rise=rise,
                          history=history))
    if not out:
        raise FitError(f"no usable transient window ({len(segs)} steps found); each needs "
                       f"{min_s} s without missing samples before the next step.")
    n = min(w.n_samples for w in out)
    return tuple(w.trimmed(n) for w in out)


def windows_from_recording(rec: Any, mill: Mill, *, segments: Iterable[Any] | None = None,
                           window_s: float = 0.45, pre_s: float = 0.05,
                           rate_hz: float = 1000.0, min_s: float = 0.3) -> tuple[Window, ...]:
    """Windows of every bite and release of a recording (see :func:`windows_from_frame`).

    Parameters
    ----------
    rec : Recording
        As read by :func:`ident.io.read_recording`.
    mill : Mill
    segments : iterable of Segment, optional
        Default: :func:`ident.segment.segment_transients` of ``rec``.

    Raises
    ------
    RecordingError
        No torque channel of the mill file in the recording.
    FitError
        No usable window.
    """
    from ..io.readers import reduced_torques
    from ..segment import segment_transients

    if not any(c.name in rec.channels for c in mill.torque_channels()):
        raise RecordingError(f"the discrepancy workflow needs torque channels; the mill file "
                             f"maps {[c.name for c in mill.torque_channels()]}, the recording "
                             f"holds {list(rec.channels)}", path=rec.path)
    if segments is None:
        segments = segment_transients(rec, mill)
    return windows_from_frame(reduced_torques(rec, mill), mill, segments, window_s=window_s,
                              pre_s=pre_s, rate_hz=rate_hz, min_s=min_s)


def as_windows(items: Iterable[Any]) -> tuple[Window, ...]:
    """Coerce windows built elsewhere (``FitWindow`` and the like) to :class:`Window`.

    Bars are assigned in time order: every bite starts a new bar.  Levels come
    from ``level_before``/``level_after`` or from ``static_torque`` and ``step``.
    """
    items = sorted(items, key=lambda w: float(w.t[0]))
    out: list[Window] = []
    bar = -1
    for w in items:
        if isinstance(w, Window):
            out.append(w)
            bar = max(bar, w.bar)
            continue
        if w.kind == "bite" or bar < 0:
            bar += 1
        before = getattr(w, "level_before", None)
        after = getattr(w, "level_after", None)
        if before is None or after is None:
            st, step = float(w.static_torque), float(w.step)
            before, after = (st - step, st) if w.kind == "bite" else (st, st + step)
        out.append(Window(t=w.t, elements=tuple(w.elements), y=w.y, t_step=float(w.t_step),
                          kind=w.kind, level_before=float(before), level_after=float(after),
                          bar=bar, label=getattr(w, "label", "")))
    if not out:
        raise FitError("the discrepancy workflow needs at least one window. Got none.")
    n = min(w.n_samples for w in out)
    return tuple(w.trimmed(n) for w in out)
