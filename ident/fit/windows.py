"""Transient windows: the measured data one fit looks at.

A :class:`FitWindow` is one load-step transient cut from a recording: uniformly
sampled reduced torques of the measured elements plus what the segmenter
estimated about the step (its half-height time, kind, levels), which seeds the
load ramp.  :func:`windows_from_recording` cuts them from a
:class:`~ident.io.recording.Recording` and the segments of
``ident.segment.segment_transients``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..description import Mill, Quantity
from ..errors import DataQualityWarning, FitError
from .noise import NoiseSpectrum, noise_spectrum

__all__ = ["FitWindow", "windows_from_recording", "reduced_torque_frame"]


@dataclass(frozen=True, eq=False)
class FitWindow:
    """One transient window of measured reduced torques.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sample times, s from the recording's start, uniformly spaced.
    elements : tuple of str
        Element ids of the torque columns of ``y``.
    y : ndarray, shape (N, len(elements))
        Measured torques reduced to the motor shaft, N*m (physical / ratio).
    t_step : float
        Half-height instant of the load step, s (segmenter estimate).
    kind : str
        ``"bite"`` or ``"release"``.
    static_torque : float
        Rolling level of the bar, N*m reduced (after a bite, before a release).
    step : float
        Change of the load, N*m reduced (negative for a release).
    label : str
        Where the window came from (for reports).
    noise : NoiseSpectrum or None
        The sensor noise's density per element, measured on the quiet
        stretches of the recording the window was cut from (the same object
        for every window of one recording; :mod:`ident.fit.noise`).  None:
        the fit estimates it from the windows themselves.
    """

    t: np.ndarray
    elements: tuple[str, ...]
    y: np.ndarray
    t_step: float
    kind: str = "bite"
    static_torque: float = 0.0
    step: float = 0.0
    label: str = ""
    meta: Mapping[str, Any] = field(default_factory=dict)
    noise: NoiseSpectrum | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        y = np.asarray(self.y, dtype=float)
        if y.ndim == 1:
            y = y[:, None]
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "elements", tuple(self.elements))
        if t.ndim != 1 or t.size < 8:
            raise FitError(f"FitWindow {self.label!r}: t must be a 1-D array of at least 8 "
                           f"samples. Got shape {t.shape}.")
        if y.shape != (t.size, len(self.elements)):
            raise FitError(f"FitWindow {self.label!r}: y must have shape (len(t), "
                           f"len(elements)) = ({t.size}, {len(self.elements)}). Got {y.shape}.")
        dt = np.diff(t)
        if not np.all(dt > 0) or np.ptp(dt) > 1e-6 * dt.mean() + 1e-12:
            raise FitError(f"FitWindow {self.label!r}: samples must be uniformly spaced in time.")
        if not np.all(np.isfinite(y)):
            raise FitError(f"FitWindow {self.label!r}: torques contain NaN or inf; cut windows "
                           "around dropouts.")
        if self.kind not in ("bite", "release"):
            raise FitError(f"FitWindow {self.label!r}: kind must be 'bite' or 'release'. "
                           f"Got {self.kind!r}.")

    @property
    def dt(self) -> float:
        """Sample interval, s."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.dt

    @property
    def n_samples(self) -> int:
        return int(self.t.size)

    @property
    def level_before(self) -> float:
        """Load before the step, N*m reduced."""
        return self.static_torque - self.step if self.kind == "bite" else self.static_torque

    @property
    def level_after(self) -> float:
        """Load after the step, N*m reduced."""
        return self.static_torque if self.kind == "bite" else self.static_torque + self.step

    def trimmed(self, n_samples: int) -> "FitWindow":
        """The first ``n_samples`` samples of this window."""
        return FitWindow(t=self.t[:n_samples], elements=self.elements, y=self.y[:n_samples],
                         t_step=self.t_step, kind=self.kind, static_torque=self.static_torque,
                         step=self.step, label=self.label, meta=self.meta, noise=self.noise)

    def with_noise(self, noise: NoiseSpectrum | None) -> "FitWindow":
        """This window with the recording's noise spectrum attached."""
        import dataclasses
        return dataclasses.replace(self, noise=noise)

    @classmethod
    def from_frame(cls, frame: pd.DataFrame, mill: Mill, *, t_start: float, t_end: float,
                   t_step: float, kind: str = "bite", static_torque: float = 0.0,
                   step: float = 0.0, label: str = "") -> "FitWindow":
        """Cut ``[t_start, t_end)`` from a frame of reduced torques indexed by ``time_s``.

        Columns may be element ids (``C46``), output names (``tau:C46``) or the
        mill's torque channel names (``T_C46``).
        """
        cols = _element_columns(frame, mill)
        t = frame.index.to_numpy(dtype=float)
        m = (t >= t_start - 1e-9) & (t < t_end - 1e-9)
        return cls(t=t[m], elements=tuple(cols), y=frame.loc[m, list(cols.values())].to_numpy(),
                   t_step=t_step, kind=kind, static_torque=static_torque, step=step,
                   label=label)


def _element_columns(frame: pd.DataFrame, mill: Mill) -> dict[str, str]:
    """Map element id -> column of ``frame`` holding its reduced torque."""
    out: dict[str, str] = {}
    names = {c.name: c.element for c in mill.torque_channels()}
    for col in frame.columns:
        c = str(col)
        eid = c[4:] if c.startswith("tau:") else names.get(c, c)
        if eid in mill.element_ids and eid not in out:
            out[eid] = col
    if not out:
        raise FitError("no reduced torque column matches an element of mill "
                       f"'{mill.name}'. Got columns {list(frame.columns)}; expected element ids "
                       f"{list(mill.element_ids)} or channel names {list(names)}.")
    return out


def reduced_torque_frame(rec: Any, mill: Mill) -> pd.DataFrame:
    """Reduced torques (N*m) of the mill's torque channels, one column per element id.

    Uses ``ident.io.readers.reduced_torques`` when available, else divides each
    torque channel's SI physical torque by its element's ``ratio``.
    """
    try:
        from ..io.readers import reduced_torques  # type: ignore[attr-defined]
    except ImportError:
        reduced_torques = None
    if reduced_torques is not None:
        return reduced_torques(rec, mill)
    cols = {}
    for ch in mill.torque_channels():
        if ch.name in rec.channels:
            cols[ch.element] = rec.channel(ch.name) / mill.element(ch.element).ratio
    if not cols:
        raise FitError(f"the recording has none of mill '{mill.name}''s torque channels "
                       f"{[c.name for c in mill.torque_channels()]}. Got {list(rec.channels)}.")
    return pd.DataFrame(cols)


def windows_from_recording(rec: Any, mill: Mill, segments: Iterable[Any], *,
                           window_s: float = 0.3, pre_s: float = 0.05,
                           max_windows: int | None = 4,
                           kinds: Sequence[str] = ("bite", "release"),
                           min_s: float = 0.25) -> tuple[FitWindow, ...]:
    """Cut fit windows around the segmented transients of a recording.

    Each window starts ``pre_s`` before the segment's ``t_step`` and lasts
    ``window_s``, cut short before the next transient's start (a window must
    hold one load step only); windows shorter than ``min_s`` or with missing
    samples are left out (with a :class:`~ident.errors.DataQualityWarning`).
    Releases matter: the unloading swings every element across its gap to the
    back flank, which is what shows the *total* gap; a bite from rest shows
    the open part.

    Parameters
    ----------
    rec : Recording
    mill : Mill
    segments : iterable of Segment
        With ``t_start, t_step, t_end, kind, static_torque, step`` (s, N*m reduced).
    window_s, pre_s, min_s : float
        Window length, lead before ``t_step`` and shortest accepted window, s.
    max_windows : int or None
        Keep at most this many, alternating between ``kinds`` in time order.
    kinds : sequence of str
        Segment kinds to use.

    Returns
    -------
    tuple of FitWindow
        All of one length (the shortest accepted), so that one NLP serves all.

    Raises
    ------
    FitError
        No usable window.
    """
    frame = reduced_torque_frame(rec, mill)
    segs = sorted(segments, key=lambda s: s.t_step)
    t_end_rec = float(frame.index[-1]) if len(frame) else 0.0
    per_kind: dict[str, list[FitWindow]] = {k: [] for k in kinds}
    for i, s in enumerate(segs):
        if s.kind not in per_kind:
            continue
        t0 = s.t_step - pre_s
        t1 = t0 + window_s
        if i + 1 < len(segs):
            nxt = segs[i + 1]
            t1 = min(t1, min(nxt.t_start, nxt.t_step - 0.03))
        t1 = min(t1, t_end_rec)
        if t0 < float(frame.index[0]) or t1 - t0 < min_s:
            continue
        try:
            w = FitWindow.from_frame(frame, mill, t_start=t0, t_end=t1, t_step=s.t_step,
                                     kind=s.kind, static_torque=float(s.static_torque),
                                     step=float(s.step), label=f"{s.kind}@{s.t_step:.3f}s")
        except FitError as exc:
            warnings.warn(f"window at t={s.t_step:.3f} s left out: {exc}", DataQualityWarning,
                          stacklevel=2)
            continue
        per_kind[s.kind].append(w)
    chosen: list[FitWindow] = []
    queues = [list(v) for v in per_kind.values()]
    while any(queues) and (max_windows is None or len(chosen) < max_windows):
        for q in queues:
            if q and (max_windows is None or len(chosen) < max_windows):
                chosen.append(q.pop(0))
    if not chosen:
        raise FitError(f"no usable transient window of kinds {tuple(kinds)} in the recording "
                       f"({len(segs)} segments found); expected at least one step of "
                       f"{min_s} s without missing samples.")
    n = min(w.n_samples for w in chosen)
    chosen.sort(key=lambda w: w.t[0])
    noise = recording_noise(frame, mill, segs, n)
    return tuple(w.trimmed(n).with_noise(noise) for w in chosen)


#: Time after a load step's half-height instant left out of the noise estimate, s
#: (the ring-down of the modes above the transient band has decayed by then).
RING_DOWN_S = 0.5

#: Most segments the noise estimate takes (evenly spread over a long recording).
MAX_NOISE_SEGMENTS = 400


def recording_noise(frame: pd.DataFrame, mill: Mill, segments: Sequence[Any], n: int
                    ) -> NoiseSpectrum | None:
    """The sensor noise's density per element on the quiet stretches of a recording.

    Every load step is left out from its segment's ``t_start`` (less 50 ms)
    to :data:`RING_DOWN_S` after its ``t_step``; segments are ``n`` samples
    long (the fit windows' length).  None when fewer than 8 quiet segments
    remain (the fit then estimates the noise from its windows).
    """
    t = frame.index.to_numpy(dtype=float)
    if t.size < 2 * n:
        return None
    from ..model.linear import natural_modes
    from .noise import bands

    cols = _element_columns(frame, mill)
    y = frame[list(cols.values())].to_numpy(dtype=float)
    dt = float(np.median(np.diff(t)))
    band = bands(natural_modes(mill).frequencies_hz, 1.0 / dt, n * dt).noise
    exclude = [(float(s.t_start) - 0.05, float(s.t_step) + RING_DOWN_S) for s in segments]
    return noise_spectrum(t, y, list(cols), segment_n=n, exclude=exclude,
                          max_segments=MAX_NOISE_SEGMENTS, band=band)

