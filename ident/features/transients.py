"""Load-step transients in a recording, in the form the features read them.

The features need, per bar, where the load step sits (``t_step``), which way
it goes (bite or release), the rolling level and the step height, and the
torque signals reduced to the motor shaft.  Segmentation proper is
``ident.segment``'s job; here its results (or any approximate step times, e.g.
a simulation's scenario) are refined the same way for the recordings the
classifier is trained on and the ones it diagnoses, so that phases referred to
``t_step`` compare:

* ``t_step`` is the instant the summed torque of the channel(s) nearest the
  rolls crosses half the step height (cli.md, ``segment``), interpolated
  between samples;
* the levels before and after are medians over windows clear of the ringing's
  first cycles.

Torques are reduced (physical / ``ratio``), N*m; times in s from the
recording's start.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

import numpy as np

from ..description import Mill, Quantity
from ..errors import RecordingError
from ..io.recording import Recording
from ..segment import distance_to_load, load_fractions

__all__ = ["Kind", "Transient", "Signal", "torque_signals", "acceleration_signals",
           "static_shares", "nearest_load_elements", "refine_transients", "transients_from_segments",
           "find_steps", "half_crossing", "reference_signal"]


class Kind(str, enum.Enum):
    """Direction of a load step."""

    BITE = "bite"
    RELEASE = "release"


@dataclass(frozen=True)
class Transient:
    """One load step, refined on the data.

    Attributes
    ----------
    t_step : float
        Half-height instant of the step in the summed torque nearest the rolls, s.
    kind : Kind
    static_torque : float
        Rolling level of the bar (after a bite, before a release), total load
        reduced to the motor shaft, N*m.
    step : float
        Change of the total reduced load, N*m (negative for a release).
    t_prev, t_next : float
        Previous and next steps (or the recording's ends), s: windows stop there.
    """

    t_step: float
    kind: Kind
    static_torque: float
    step: float
    t_prev: float = -np.inf
    t_next: float = np.inf


@dataclass(frozen=True)
class Signal:
    """One channel's samples in SI (reduced for torques).

    Attributes
    ----------
    name : str
        Channel name.
    target : str
        Element id (torque) or ``"BID:v"``/``"BID:h"`` (acceleration).
    t0 : float
        Time of the first sample, s.
    rate_hz : float
    x : ndarray
        Samples; gaps (NaN) interpolated.
    """

    name: str
    target: str
    t0: float
    rate_hz: float
    x: np.ndarray

    def index(self, t: float) -> int:
        """Nearest sample index of time ``t`` (s), clipped to the signal."""
        return int(np.clip(round((t - self.t0) * self.rate_hz), 0, self.x.size - 1))

    def window(self, t_a: float, t_b: float) -> np.ndarray:
        """Samples with ``t_a <= t < t_b``."""
        i = max(int(np.ceil((t_a - self.t0) * self.rate_hz - 1e-9)), 0)
        j = min(int(np.ceil((t_b - self.t0) * self.rate_hz - 1e-9)), self.x.size)
        return self.x[i:j] if j > i else self.x[:0]

    def at(self, t: np.ndarray) -> np.ndarray:
        """Linear interpolation at times ``t`` (s)."""
        tt = self.t0 + np.arange(self.x.size) / self.rate_hz
        return np.interp(t, tt, self.x)

    @property
    def t_end(self) -> float:
        return self.t0 + (self.x.size - 1) / self.rate_hz


def _fill(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    bad = ~np.isfinite(x)
    if bad.all():
        return np.zeros_like(x)
    if bad.any():
        idx = np.arange(x.size)
        x = x.copy()
        x[bad] = np.interp(idx[bad], idx[~bad], x[~bad])
    return x


def _series(rec: Recording, name: str) -> tuple[float, float, np.ndarray]:
    dev = rec.device_of(name)
    frame = rec.frames[dev]
    t = frame.index.to_numpy(dtype=float)
    rate = float(rec.rates_hz[dev])
    return (float(t[0]) if t.size else 0.0), rate, _fill(frame[name].to_numpy())


def torque_signals(rec: Recording, mill: Mill) -> dict[str, Signal]:
    """The recording's torque channels reduced to the motor shaft, by element id.

    Raises
    ------
    RecordingError
        When the recording holds none of the mill's torque channels.
    """
    out: dict[str, Signal] = {}
    for ch in mill.torque_channels():
        if ch.name not in rec.channels or ch.element in out:
            continue
        t0, rate, x = _series(rec, ch.name)
        out[ch.element] = Signal(ch.name, ch.element, t0, rate, x / mill.element(ch.element).ratio)
    if not out:
        raise RecordingError(f"no torque channel of mill '{mill.name}' in the recording; "
                             f"expected one of {[c.name for c in mill.torque_channels()]}",
                             path=rec.path)
    return out


def acceleration_signals(rec: Recording, mill: Mill) -> dict[str, Signal]:
    """The recording's housing accelerations (m/s^2), keyed ``"BID:v"`` / ``"BID:h"``."""
    out: dict[str, Signal] = {}
    for ch in mill.acceleration_channels():
        if ch.name not in rec.channels:
            continue
        key = f"{ch.bearing}:{'v' if ch.direction == 'vertical' else 'h'}"
        t0, rate, x = _series(rec, ch.name)
        out[key] = Signal(ch.name, key, t0, rate, x)
    return out


def static_shares(mill: Mill) -> dict[str, float]:
    """Share of the total rolling load each element carries at rest (1, reduced).

    :func:`ident.segment.load_fractions`, named for this module's readers.
    """
    return load_fractions(mill)


def nearest_load_elements(mill: Mill, element_ids: Iterable[str]) -> tuple[str, ...]:
    """Of ``element_ids``, those nearest the rolls (:func:`ident.segment.distance_to_load`)."""
    ids = list(element_ids)
    dist = distance_to_load(mill)
    best = min(dist[e] for e in ids)
    return tuple(e for e in ids if dist[e] == best)


def reference_signal(signals: Mapping[str, Signal], mill: Mill) -> tuple[Signal, float]:
    """Summed torque of the channels nearest the rolls and its static share."""
    near = nearest_load_elements(mill, signals)
    shares = static_shares(mill)
    base = signals[near[0]]
    x = base.x.copy()
    share = shares[near[0]]
    for e in near[1:]:
        s = signals[e]
        x = x + (s.x[:x.size] if s.rate_hz == base.rate_hz and s.x.size >= x.size
                 else s.at(base.t0 + np.arange(x.size) / base.rate_hz))
        share += shares[e]
    return Signal("+".join(signals[e].name for e in near), "+".join(near), base.t0, base.rate_hz,
                  x), share


def _levels(ref: Signal, t: float, lo: float, hi: float) -> tuple[float, float]:
    pre = ref.window(max(t - 0.25, lo), t - 0.04)
    post = ref.window(t + 0.25, min(t + 0.6, hi))
    if pre.size < 3:
        pre = ref.window(max(t - 0.1, lo, ref.t0), t - 0.02)
    if post.size < 3:
        post = ref.window(t + 0.1, min(t + 0.3, hi))
    a = float(np.median(pre)) if pre.size else float(ref.x[0])
    b = float(np.median(post)) if post.size else float(ref.x[-1])
    return a, b


def half_crossing(ref: Signal, t: float, level: float, rising: bool, span: float) -> float | None:
    """Time (s) where ``ref`` crosses ``level`` within ``t +- span``, nearest ``t``; None if never."""
    i0 = ref.index(t - span)
    i1 = ref.index(t + span)
    seg = ref.x[i0:i1 + 1] - level
    if not rising:
        seg = -seg
    idx = np.flatnonzero((seg[:-1] < 0) & (seg[1:] >= 0))
    if idx.size == 0:
        return None
    # the crossing nearest the approximate time
    tt = ref.t0 + (i0 + idx) / ref.rate_hz
    k = idx[np.argmin(np.abs(tt - t))]
    frac = -seg[k] / (seg[k + 1] - seg[k]) if seg[k + 1] != seg[k] else 0.0
    return ref.t0 + (i0 + k + frac) / ref.rate_hz


def refine_transients(signals: Mapping[str, Signal], mill: Mill, t_steps: Iterable[float], *,
                      min_step: float = 0.0) -> tuple[Transient, ...]:
    """Refine approximate step times on the torque signals.

    Parameters
    ----------
    signals : mapping
        :func:`torque_signals` of the recording.
    mill : Mill
    t_steps : iterable of float
        Approximate step times, s (a segmentation's ``t_step`` or a scenario's).
    min_step : float
        Steps of smaller total height (N*m, reduced) are dropped.

    Returns
    -------
    tuple of Transient
        Sorted by time; ``t_prev``/``t_next`` link neighbours.
    """
    ref, share = reference_signal(signals, mill)
    ts = sorted(float(t) for t in t_steps)
    bounds = [ref.t0] + ts + [ref.t_end]
    raw = []
    for i, t in enumerate(ts):
        lo, hi = 0.5 * (bounds[i] + t), 0.5 * (t + bounds[i + 2])
        pre, post = _levels(ref, t, lo, hi)
        step = post - pre
        if abs(step) / max(abs(share), 1e-12) <= min_step or step == 0.0:
            continue
        tc = half_crossing(ref, t, pre + 0.5 * step, step > 0, span=0.06)
        if tc is None:
            tc = t
        total_step = step / share
        kind = Kind.BITE if step > 0 else Kind.RELEASE
        static = (post if kind is Kind.BITE else pre) / share
        raw.append((tc, kind, static, total_step))
    out = []
    for i, (tc, kind, static, st) in enumerate(raw):
        tp = raw[i - 1][0] if i > 0 else ref.t0
        tn = raw[i + 1][0] if i + 1 < len(raw) else ref.t_end
        out.append(Transient(t_step=tc, kind=kind, static_torque=static, step=st, t_prev=tp,
                             t_next=tn))
    return tuple(out)


def transients_from_segments(segments: Iterable[Any]) -> tuple[float, ...]:
    """Step times (s) of ``ident.segment`` segments (anything with ``t_step``)."""
    out = []
    for s in segments:
        t = s["t_step"] if isinstance(s, Mapping) else getattr(s, "t_step")
        out.append(float(t))
    return tuple(out)


def find_steps(signals: Mapping[str, Signal], mill: Mill, *, min_fraction: float = 0.1,
               smooth_s: float = 0.05, min_gap_s: float = 0.3) -> tuple[float, ...]:
    """Approximate load-step times from the torque nearest the rolls (a fallback).

    Used when no segmentation is given: smooths the summed torque nearest the
    rolls over ``smooth_s``, takes its derivative and returns the times of its
    extrema larger than ``min_fraction`` of the largest step, at least
    ``min_gap_s`` apart.

    Returns
    -------
    tuple of float
        Times, s.
    """
    ref, _ = reference_signal(signals, mill)
    n = max(int(round(smooth_s * ref.rate_hz)), 1)
    k = np.ones(n) / n
    xs = np.convolve(ref.x, k, mode="same")
    lag = max(int(round(0.02 * ref.rate_hz)), 1)
    d = np.zeros_like(xs)
    d[lag:-lag] = xs[2 * lag:] - xs[:-2 * lag]
    d[:n] = 0
    d[-n:] = 0
    mag = np.abs(d)
    if mag.max() <= 0:
        return ()
    thr = min_fraction * mag.max()
    cand = np.flatnonzero(mag >= thr)
    out: list[int] = []
    gap = int(min_gap_s * ref.rate_hz)
    # greedy: strongest first, suppress neighbours
    for i in cand[np.argsort(-mag[cand])]:
        if all(abs(i - j) > gap for j in out):
            out.append(int(i))
    return tuple(sorted(ref.t0 + i / ref.rate_hz for i in out))

