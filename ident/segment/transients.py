"""Find the load-step transients (bites and releases) in a recording.

Method (torque channels)
------------------------
1. *Signal.*  The measured torque channels nearest the rolls (smallest graph
   distance from their element to a ``[load]`` mass, :func:`~.loadshare.distance_to_load`)
   are reduced to the motor shaft (physical / ``ratio``) and divided by their
   element's static load fraction (:func:`~.loadshare.load_fractions`), giving each
   an estimate of the *total* rolling torque.  Each channel's sample noise is
   measured (MAD of differences); tied channels (the two spindles) are averaged for
   timing and levels (cli.md's torque nearest the rolls) and combined with
   inverse-variance weights for detection.
2. *Detection* (:mod:`.detect`): everything is scaled by the recording and the
   mill, nothing by a stand: the signal is smoothed over 1.25 periods of the mill's
   lowest natural mode (:func:`~.timescales.lowest_mode`) twice, so that its
   ring-down cannot cross a threshold; its idle level and smallest bar are read off
   its plateaus; the hysteresis sits at 50 % / 25 % of that smallest bar above
   idle, and a step must exceed 12 noise sigma, half the smallest bar and 6 times
   the spread of the levels either side (a drift is no step).
3. *Levels.*  The level before and after each step: medians of the smoothed
   signal over ``level_s`` windows that keep clear of the step (1.25 periods plus
   50 ms), skip ``settle_s`` of ring-down after it and stop short of the
   neighbouring steps (short pauses shrink them).
4. *Timing.*  ``t_step`` is the first crossing of the half-way level (pre + post) / 2
   by the lightly smoothed (``fine_s`` = 2.5 ms) signal near the smoothed signal's
   own crossing, linearly interpolated between samples (cli.md: "the moment the
   step reaches half its height").
5. *Windows.*  ``t_start = t_step - pre_s``; ``t_end`` is when the ring-down has
   decayed (its running maximum deviation from the new level over one period of the
   lowest mode falls below ``decay_fraction`` of the step, or 4 noise sigma), kept
   within ``[min_window_s, max_window_s]`` after ``t_step`` and always ``pre_s``
   before the next step, so windows never overlap.  A window stops before a
   dropout; a step whose timing region holds a dropout is skipped.

Torques in the result are totals reduced to the motor shaft, N*m.  Levels are taken
relative to the idle level next to the step (the telemetry zero drifts; the no-load
torque of the drive counts as zero), so ``static_torque`` is the rolling level of
the bar, ``step = static_torque`` for a bite and ``-static_torque`` for a release.

Accelerometer-only recordings
-----------------------------
Without torque channels the same detection runs on the vibration envelope: the RMS of
all acceleration channels over ``envelope_s`` (10 ms), at 1 kHz.  The housing
vibration grows with the mesh load, so bites and releases show as envelope steps.
``static_torque`` and ``step`` are then NaN (no torque is measured) and ``channel``
names the accelerometers.  Precision against the torque half-height time, asserted
in ``tests/test_segment.py``: bites within 5 ms, releases within 40 ms (the housing
ring-down at a release keeps the envelope up for a few tens of ms).

Measured precision
------------------
On the synthetic stand of ``tests/synth_telemetry.py`` (10 seeds, 60 s each, 194
steps, 30-40 dB noise, 10-40 ms ramps): torque ``t_step`` error at most 0.85 ms
(median 0.1 ms), ``static_torque`` and ``step`` within 1.7 % (rms 0.5 %; the load
fluctuates by up to 2 % while rolling), no missed or extra step; accelerometers only:
bites -3.2 ms (at most 3.6 ms), releases +28.5 ms (at most 32 ms).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ..description import Mill
from ..errors import RecordingError
from ..io.readers import reduced_torques
from ..io.recording import Recording
from .detect import Event, detect_steps, moving_mean, noise_sigma
from .loadshare import distance_to_load, load_fractions
from .timescales import lowest_mode

__all__ = ["Segment", "segment_transients"]


@dataclass(frozen=True)
class Segment:
    """One load-step transient.

    Attributes
    ----------
    t_start, t_step, t_end : float
        Seconds from the recording's start: the window a fit should use, and the
        moment the step reaches half its height in the torque nearest the rolls.
    kind : {"bite", "release"}
    static_torque : float
        Rolling level of the bar (after a bite, before a release) as the total rolling
        torque reduced to the motor shaft, N*m; NaN for accelerometer-only recordings.
    step : float
        The change, N*m, same reduction; negative for a release; NaN without torque.
    channel : str
        The channel that timed the step (the first of ``channels``).
    channels : tuple of str
        All channels combined into the detection signal.
    rise_s : float
        10-90 % rise (or fall) time of the step, s.
    """

    t_start: float
    t_step: float
    t_end: float
    kind: Literal["bite", "release"]
    static_torque: float
    step: float
    channel: str
    channels: tuple[str, ...] = ()
    rise_s: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        """The ``segment`` JSON entry of cli.md (plus ``channel`` and ``rise_s``)."""
        return {"t_start": self.t_start, "t_step": self.t_step, "t_end": self.t_end,
                "kind": self.kind, "static_torque": self.static_torque, "step": self.step,
                "channel": self.channel, "rise_s": self.rise_s}


# ---- windows -------------------------------------------------------------------------------
def _running_max_ahead(x: np.ndarray, w: int) -> np.ndarray:
    """max(x[i:i+w]) for each i (NaN-free input)."""
    from scipy.ndimage import maximum_filter1d

    w = max(1, int(w))
    return maximum_filter1d(x, size=w, origin=-(w // 2), mode="nearest")


def _windows(events: list[Event], xs: np.ndarray, fs: float, sigma: float, *, pre_s: float,
             min_window_s: float, max_window_s: float, decay_fraction: float,
             decay_window_s: float) -> list[tuple[float, float, float]]:
    """(t_start, t_step, t_end), s from the signal's first sample, for each event."""
    n = xs.size
    out: list[tuple[float, float, float]] = []
    for k, ev in enumerate(events):
        t_step = ev.i_step / fs
        t_next = events[k + 1].i_step / fs if k + 1 < len(events) else math.inf
        t_start = max(t_step - pre_s, 0.0, out[-1][2] if out else 0.0)
        limit = max(min(t_step + max_window_s, t_next - pre_s, (n - 1) / fs), t_step)
        t_end = limit
        a = int(math.ceil((t_step + 0.05) * fs))
        b = int(math.floor(limit * fs)) + 1
        if b > a:
            seg = xs[a:b]
            nan_at = np.flatnonzero(np.isnan(seg))
            if nan_at.size:  # stop before a dropout
                seg = seg[: nan_at[0]]
                t_end = max((a + int(nan_at[0]) - 1) / fs, t_step)
            if seg.size:
                dev = _running_max_ahead(np.abs(seg - ev.post), int(round(decay_window_s * fs)))
                thr = max(decay_fraction * abs(ev.post - ev.pre), 4.0 * sigma)
                ok = np.flatnonzero(dev < thr)
                if ok.size:
                    t_decay = (a + int(ok[0])) / fs + decay_window_s
                    t_end = min(t_end, max(t_decay, t_step + min_window_s))
        out.append((t_start, t_step, t_end))
    return out


def segment_transients(rec: Recording, mill: Mill, *, pre_s: float = 0.1,
                       min_window_s: float = 0.3, max_window_s: float = 0.8,
                       decay_fraction: float = 0.05, decay_window_s: float | None = None,
                       smooth_s: float | None = None, fine_s: float = 0.0025,
                       level_s: float = 0.5, settle_s: float = 0.35,
                       min_step: float | None = None,
                       envelope_s: float = 0.01) -> tuple[Segment, ...]:
    """Find every bite (load step up) and release (step down) in a recording.

    Every threshold comes from the mill and the recording (module docstring): the
    smoothing and the ring-down span from the period of the mill's lowest natural
    mode, the noise floor from each channel's sample noise, the hysteresis from the
    recording's idle level and its smallest bar.

    Parameters
    ----------
    rec : Recording
        As read by :func:`ident.io.read_recording` (SI, physical shaft torques).
    mill : Mill
        Sensor map, ratios, load shares and graph (to pick the channel nearest the
        rolls), inertias and stiffnesses (its lowest natural mode).
    pre_s : float
        Window start before ``t_step``, s (50-100 ms of the idle/rolling level).
    min_window_s, max_window_s : float
        Bounds of ``t_end - t_step``, s.
    decay_fraction : float
        The ring-down has decayed when its deviation from the new level stays below
        this fraction of the step (or 4 noise sigma) for ``decay_window_s``.
    decay_window_s : float, optional
        Span the deviation must stay small, s; default one period of the lowest mode.
    smooth_s : float, optional
        Length of each of the two cascaded moving means the detection smooths with,
        s; default 1.25 periods of the lowest mode.
    fine_s : float
        Moving mean for timing, s.
    level_s, settle_s : float
        Length of the level windows and the ring-down skipped before the level after a
        step, s.
    min_step : float, optional
        Smallest step reported, N*m total reduced (or envelope m/s^2 without torque);
        default: 12 noise sigma and half the recording's smallest bar.
    envelope_s : float
        RMS window of the vibration envelope (accelerometer-only recordings), s.

    Returns
    -------
    tuple of Segment
        In time order; kinds alternate unless a step could not be timed.

    Raises
    ------
    RecordingError
        The recording has no torque channel with a static load and no acceleration
        channel of the mill file.
    """
    for name, v in (("pre_s", pre_s), ("min_window_s", min_window_s),
                    ("max_window_s", max_window_s), ("smooth_s", smooth_s),
                    ("decay_window_s", decay_window_s), ("level_s", level_s)):
        if v is None and name in ("smooth_s", "decay_window_s"):
            continue
        if not (isinstance(v, (int, float)) and v > 0):
            raise ValueError(f"segment_transients: {name} must be a positive number of "
                             f"seconds; got {v!r}")
    if min_window_s > max_window_s:
        raise ValueError(f"segment_transients: min_window_s ({min_window_s}) must not exceed "
                         f"max_window_s ({max_window_s})")
    period = lowest_mode(mill).period_s
    fractions = load_fractions(mill)
    dist = distance_to_load(mill)
    torque = [c for c in mill.torque_channels()
              if c.name in rec.channels and abs(fractions.get(c.element, 0.0)) > 0.05]
    opts = dict(period_s=period, smooth_s=smooth_s, fine_s=fine_s, level_s=level_s,
                settle_s=settle_s, min_step=min_step)
    wopts = dict(pre_s=pre_s, min_window_s=min_window_s, max_window_s=max_window_s,
                 decay_fraction=decay_fraction,
                 decay_window_s=decay_window_s if decay_window_s is not None else period)
    if torque:
        d_min = min(dist[c.element] for c in torque)
        near = [c for c in torque if dist[c.element] == d_min]
        red = reduced_torques(rec, mill)
        fs = 1.0 / float(np.median(np.diff(red.index.to_numpy()[:1000])))
        # each channel's estimate of the total rolling torque and its own noise
        est = [red[c.name].to_numpy(dtype=np.float64) / fractions[c.element] for c in near]
        sig = np.array([noise_sigma(v) for v in est])
        x = np.mean(est, axis=0)  # cli.md: t_step on the torque nearest the rolls (averaged)
        sigma = float(np.sqrt(np.sum(sig ** 2))) / len(est)
        x_det, sigma_det = None, None
        if len(est) > 1 and np.all(sig > 0):
            w = sig ** -2 / np.sum(sig ** -2)  # detect on the least noisy combination
            x_det = np.sum([wi * v for wi, v in zip(w, est)], axis=0)
            sigma_det = float(np.sum(sig ** -2) ** -0.5)
        t0 = float(red.index[0])
        names = tuple(c.name for c in near)
        events, xs, _ = detect_steps(x, fs, x_detect=x_det, sigma_detect=sigma_det, **opts)
        wins = _windows(events, xs, fs, sigma, **wopts)
        out = []
        for ev, (ts, tp, te) in zip(events, wins):
            static = ev.post - ev.pre if ev.kind == "bite" else ev.pre - ev.post
            out.append(Segment(t_start=t0 + ts, t_step=t0 + tp, t_end=t0 + te, kind=ev.kind,
                               static_torque=float(static), step=float(ev.post - ev.pre),
                               channel=names[0], channels=names, rise_s=ev.rise))
        return tuple(out)
    accel = [c.name for c in mill.acceleration_channels() if c.name in rec.channels]
    if not accel:
        raise RecordingError(
            "nothing to segment: the recording has no torque channel with a static load and no "
            f"acceleration channel of the mill file (it holds {list(rec.channels)}; the mill "
            f"file maps {[c.name for c in mill.channels]})", path=rec.path)
    return _segment_envelope(rec, accel, envelope_s=envelope_s, opts=opts, wopts=wopts)


def _segment_envelope(rec: Recording, names: list[str], *, envelope_s: float, opts: dict,
                      wopts: dict) -> tuple[Segment, ...]:
    """Segment from the RMS vibration envelope, resampled to 1 kHz."""
    devs = {rec.device_of(n) for n in names}
    dev = max(devs, key=lambda d: sum(n in rec.frames[d].columns for n in names))
    cols = [n for n in names if n in rec.frames[dev].columns]
    frame = rec.frames[dev]
    fs_in = rec.rates_hz[dev]
    power = np.zeros(len(frame))
    for c in cols:
        v = frame[c].to_numpy(dtype=np.float64)
        v = v - np.nanmedian(v[:: max(1, v.size // 1_000_000)])
        power += v * v
    env = np.sqrt(moving_mean(power, int(round(envelope_s * fs_in))))
    step = max(1, int(round(fs_in / 1000.0)))
    x = env[::step]
    fs = fs_in / step
    t0 = float(frame.index[0])
    lag = max(1, int(round(envelope_s * fs)))
    events, xs, _ = detect_steps(x, fs, noise_lag=lag, **opts)
    sigma = noise_sigma(x, lag)
    wins = _windows(events, xs, fs, sigma, **wopts)
    return tuple(Segment(t_start=t0 + ts, t_step=t0 + tp, t_end=t0 + te, kind=ev.kind,
                         static_torque=math.nan, step=math.nan, channel=cols[0],
                         channels=tuple(cols), rise_s=ev.rise)
                 for ev, (ts, tp, te) in zip(events, wins))
