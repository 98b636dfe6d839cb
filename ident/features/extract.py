"""Wear features of a recording's load-step transients (seed sections 1.1, 2, 2.2).

Per transient (bite or release) and torque channel, against the linear
baseline's response to the same step (:mod:`ident.features.baseline`):

``{E}.A{f}``          amplitude at the baseline's natural frequency ``f`` (Hz,
                      rounded), per N*m of load step -- the seed's A12 ... A81;
``{E}.A{f}.ratio``    log10 of that amplitude over the baseline's;
``{E}.A{f}.phase``    phase shift against the baseline, deg in (-180, 180],
                      both referred to the step's ``t_step``;
``{E}.H2``, ``.H3``   2nd and 3rd harmonic of the channel's dominant mode,
                      measured minus baseline, per N*m of step (seed 1.3);
``{E}.residual``      RMS of measured minus baseline over the window, per N*m
                      of the channel's step;
``{E}.taf``           torque amplification factor (peak over static torque,
                      seed 1.1; for a release the undershoot below zero over
                      the rolling level) and ``{E}.taf.excess`` its excess over
                      the baseline's;
``{E}.lag_ms``        delay of the channel's own half-height crossing behind
                      the baseline's (an open gap delays the torque);
``{E}.dwell``         excess fraction of the first 0.3 s the torque stays
                      within 2 % of the step around its new level (torque
                      inside a gap);
``{E}.rise05_ms`` ...  the gap-sweep features of :mod:`ident.features.sweep`:
                      when the torque rises, how steeply (impact), how far it
                      overshoots, when it passes beyond its new level against
                      the step (back-flank contact after a release), how long
                      it sits at the new level -- normalised by the step and,
                      where physics says so, by the static torque;
``near.{...}``        the same of the summed torque nearest the rolls (the
                      spindles), when more than one channel is nearest;
``{A}-{B}.{...}``     differences of the timing ones between channels (the
                      order the load reaches them separates the elements of
                      one path);
``static``, ``rise_ms``, ``idle_level``
                      static torque over the nominal, the fitted rise time,
                      and the load between bars (before a bite, after a
                      release) over the nominal: with any, the gaps close on
                      their drive side during the pause and the bite shows
                      nothing of them.

Per transient and accelerometer (``{B}:v`` / ``{B}:h``, seed 2.2): ``rms``,
``peak`` (log10, per the housing acceleration the mesh-force step would give
the housing mass alone), ``crest``, ``kurtosis``, ``f_peak`` (Hz, the housing's
dominant response frequency), ``centroid_hz``, ``impact_ms`` (time from ``t_step`` to the first
impact), ``H2``/``H3`` (harmonics of ``f_peak`` over its amplitude), ``phase``
(deg at ``f_peak`` referred to ``t_step``), ``band{i}`` (energy fractions) and
``rms_late`` (0.25-0.6 s after the step); and the shaft's rattle in two
windows, ``{B}:{d}.hit.{...}`` and ``{B}:{d}.after.{...}``
(:mod:`ident.features.rattle`).

A recording's feature vector (:func:`recording_features`) takes the median
over its bites and over its releases (``bite.``/``release.`` prefixes) and adds
the relation between TAF and static torque over its bars (seed section 1.1:
``bite.{E}.taf_slope``, TAF per unit of static torque over the nominal
torque).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd
from threadpoolctl import threadpool_limits

from ..description import Mill
from ..io.recording import Recording
from ..model.scenario import nominal_torque
from .baseline import LinearReference, UnitResponse
from .rattle import WINDOWS, rattle_features
from .spectral import MatrixPencil, ModeEstimator, harmonic_amplitudes
from .sweep import SWEEP_FEATURES, lowpass, normalised_window, pair_differences, sweep_features
from .transients import (Kind, Signal, Transient, acceleration_signals, find_steps, half_crossing,
                         nearest_load_elements, reference_signal, refine_transients,
                         static_shares, torque_signals)

__all__ = ["FeatureOptions", "TransientFeatures", "frequency_labels", "transient_features",
           "recording_features", "feature_summary", "BAND_EDGES_HZ"]

#: band edges of the accelerometer energy fractions, Hz
BAND_EDGES_HZ: tuple[float, ...] = (0.0, 150.0, 400.0, 800.0, 1600.0, np.inf)


@dataclass(frozen=True)
class FeatureOptions:
    """How transients are turned into features.

    Attributes
    ----------
    window_s : float
        Length of the analysed window after ``t_step``, s.
    estimator : ModeEstimator
        Amplitude/phase estimator (:mod:`ident.features.spectral`); the
        matrix pencil was the most accurate when frequencies shift.
    harmonics : tuple of int
        Harmonic orders read at each channel's dominant mode.
    taf_window_s : float
        Window for the peak torque, s.
    dwell_s : float
        Window of the dwell fraction, s.
    bearing_window_s : float
        Accelerometer window after ``t_step``, s (it starts 50 ms before).
    min_window_s : float
        Transients with less time before the next step are skipped, s.
    lowpass_hz : float
        Cut-off of the low-pass the gap-sweep features read the torque through, Hz.
    sweep_before_s, sweep_after_s : float
        The gap-sweep window around ``t_step``, s.
    spectral_releases : bool
        Also read the natural-frequency amplitudes and phases at releases (the
        seed reads them after the load steps; at a release the torque rings
        down from the rolling level through the gaps' rattle, and the two
        pencils per channel are half the features' cost).

    Notes
    -----
    The default pencil decimates to about three samples per period of the
    mill's highest mode (``samples_per_period=3``): hsm-f1's 2 kHz torque by 8
    (250 Hz, above twice the 81 Hz mode) -- on
    :func:`~ident.features.spectral.benchmark_estimators`' +-3 % case as
    accurate as by 4 (0.4 % / 0.3 deg median) at a quarter of the cost (0.6 ms
    per 0.5 s window) -- and cold-s5's by 4 (500 Hz for its 138 Hz mode).  The
    decimated rate follows the mill and the recording's rate, not a constant
    that suits one of them (a fixed 8 aliased cold-s5's 138 Hz mode, and on a
    1 kHz recording hsm-f1's 81 Hz one).
    """

    window_s: float = 0.5
    estimator: Any = field(default_factory=lambda: MatrixPencil(decimate=8,
                                                                 samples_per_period=3.0))
    harmonics: tuple[int, ...] = (2, 3)
    taf_window_s: float = 0.8
    dwell_s: float = 0.3
    bearing_window_s: float = 0.25
    min_window_s: float = 0.3
    lowpass_hz: float = 150.0
    sweep_before_s: float = 0.05
    sweep_after_s: float = 0.45
    spectral_releases: bool = False


@dataclass(frozen=True)
class TransientFeatures:
    """Features of each transient of one recording.

    Attributes
    ----------
    transients : tuple of Transient
    table : DataFrame
        One row per transient (same order), one column per feature; the
        columns ``t_step``, ``kind``, ``static_torque``, ``step``, ``rise_s``
        describe the transient.
    frequencies_hz : ndarray
        The baseline's natural frequencies (gaps closed, speed loop open, as
        ``ident frequencies``) that label the ``A{f}`` features, Hz.
    ringing_hz, ringing_damping : ndarray
        The closed-loop poles paired with them (frequency, Hz, and damping
        ratio): where the estimators read the transient.
    channels : tuple of str
        Elements with a torque channel.
    accelerometers : tuple of str
        ``BID:v``/``BID:h`` keys present.
    nominal_torque : float
        N*m, reduced: the unit of the static torque in ``taf_slope``.
    """

    transients: tuple[Transient, ...]
    table: pd.DataFrame
    frequencies_hz: np.ndarray
    ringing_hz: np.ndarray
    ringing_damping: np.ndarray
    channels: tuple[str, ...]
    accelerometers: tuple[str, ...]
    nominal_torque: float


def frequency_labels(freqs_hz: Sequence[float]) -> tuple[str, ...]:
    """``A12``-style labels of natural frequencies, unique (``A12``, ``A12b`` ...)."""
    out: list[str] = []
    for f in freqs_hz:
        lab = f"A{int(round(f))}"
        while lab in out:
            lab += "b"
        out.append(lab)
    return tuple(out)


def _wrap_deg(x: np.ndarray) -> np.ndarray:
    return (np.degrees(x) + 180.0) % 360.0 - 180.0


def _levels(sig: Signal, t: float, t_prev: float, t_next: float) -> tuple[float, float]:
    lo = 0.5 * (t_prev + t) if np.isfinite(t_prev) else sig.t0
    hi = 0.5 * (t + t_next) if np.isfinite(t_next) else sig.t_end
    pre = sig.window(max(t - 0.25, lo), t - 0.04)
    post = sig.window(t + 0.25, min(t + 0.6, hi))
    if post.size < 3:
        post = sig.window(t + 0.1, min(t + 0.3, hi))
    a = float(np.median(pre)) if pre.size else float(sig.x[sig.index(t - 0.05)])
    b = float(np.median(post)) if post.size else float(sig.x[sig.index(t + 0.2)])
    return a, b


class _Superposed:
    """The linear baseline of a whole recording: every step's unit response, superposed.

    The baseline is linear in the load, so its response to the recording's
    sequence of steps is the sum of each step's response; a transient's
    window then carries the baseline's own leftover ringing from the steps
    before it, as the measurement does.
    """

    def __init__(self) -> None:
        self.steps: list[tuple[float, float, UnitResponse]] = []  # t_step, step, unit

    def add(self, t_step: float, step: float, unit: UnitResponse) -> None:
        self.steps.append((t_step, step, unit))

    def delta(self, element_id: str, t: np.ndarray, upto: float, reference: LinearReference,
              rate_hz: float) -> np.ndarray:
        """Change of the element's baseline torque since rest at times ``t`` (s), N*m."""
        out = np.zeros_like(t, dtype=float)
        for ts, st, u in self.steps:
            if ts > upto + 1e-9:
                break
            if u.rate_hz != rate_hz:
                u = reference.response(u.rise_s, rate_hz, u.near)
            out += st * u.at(element_id, t - ts)
        return out


def _torque_channel_features(sig: Signal, filt: np.ndarray, tr: Transient, base: _Superposed,
                             reference: LinearReference, *, rise_s: float, share: float,
                             static_norm: float, labels: Sequence[str], freqs: np.ndarray,
                             damping: np.ndarray, options: FeatureOptions
                             ) -> tuple[dict[str, float], dict[str, float]]:
    """One torque channel's features at one transient.

    Returns
    -------
    features : dict
        ``{E}.{name}`` to value.
    sweep : dict
        The channel's :data:`ident.features.sweep.SWEEP_FEATURES` without prefix
        (for the channel differences).
    """
    e = sig.target
    out: dict[str, float] = {}
    step = tr.step
    step_c = step * share if abs(share) > 1e-6 else step
    rate = sig.rate_hz
    t_end = min(tr.t_step + options.window_s, tr.t_next - 0.05, sig.t_end)
    d0 = 0.5 * rise_s
    pre_c, post_c = _levels(sig, tr.t_step, tr.t_prev, tr.t_next)
    i0 = int(np.ceil((tr.t_step + d0 - sig.t0) * rate - 1e-9))
    i1 = int(np.ceil((t_end - sig.t0) * rate - 1e-9))
    # gap sweep (time domain), on the low-passed torque
    y = normalised_window(filt, sig.t0, rate, tr.t_step, pre_c, step_c,
                          before_s=options.sweep_before_s, after_s=options.sweep_after_s)
    sw = sweep_features(y, rate, int(round(options.sweep_before_s * rate)), static_norm,
                        tr.t_next - 0.05 - tr.t_step)
    out.update({f"{e}.{k}": v for k, v in sw.items()})
    nan_keys = [f"{e}.{lab}{suf}" for lab in labels for suf in ("", ".ratio", ".phase")]
    nan_keys += [f"{e}.H{k}" for k in options.harmonics]
    nan_keys += [f"{e}.{k}" for k in ("residual", "taf", "taf.excess", "lag_ms", "dwell")]
    if i1 - i0 < int(0.1 * rate) or i0 < 0:
        out.update({k: np.nan for k in nan_keys})
        return out, sw

    # the baseline on one grid covering every window below, anchored at the channel's
    # measured level before the step
    lo = max(tr.t_step - 0.25, 0.5 * (tr.t_prev + tr.t_step) if np.isfinite(tr.t_prev)
             else sig.t0)
    t_hi = max(tr.t_step + max(options.window_s, options.taf_window_s, 0.6), t_end)
    t_grid = lo + np.arange(int(np.ceil((t_hi - lo) * rate)) + 1) / rate
    d_grid = base.delta(e, t_grid, tr.t_step, reference, rate)
    pre_sel = t_grid < tr.t_step - 0.04
    anchor = float(np.median(d_grid[pre_sel])) if pre_sel.any() else 0.0

    def lin_at(t: np.ndarray) -> np.ndarray:
        return pre_c + np.interp(t, t_grid, d_grid) - anchor

    post_hi = min(tr.t_step + 0.6, 0.5 * (tr.t_step + tr.t_next) if np.isfinite(tr.t_next)
                  else sig.t_end)
    t_post = np.arange(tr.t_step + 0.25, post_hi, 1.0 / rate)
    if t_post.size < 3:
        t_post = np.arange(tr.t_step + 0.1, tr.t_step + 0.3, 1.0 / rate)
    lin_level = float(np.median(lin_at(t_post)))

    t_i = sig.t0 + np.arange(i0, i1) / rate
    tau = t_i - tr.t_step
    meas = sig.x[i0:i1]
    dyn_m = meas - post_c
    dyn_l = lin_at(t_i) - lin_level
    if tr.kind is Kind.BITE or options.spectral_releases:
        # modal amplitudes and phases, referred back to t_step
        a_l, p_l = options.estimator.estimate(dyn_l / step, rate, freqs, damping)
        a_m, p_m = options.estimator.estimate(dyn_m / step, rate, freqs, damping)
        wd = 2 * np.pi * freqs * np.sqrt(np.clip(1 - damping ** 2, 0, 1))
        p_m0 = p_m - wd * tau[0]
        p_l0 = p_l - wd * tau[0]
        eps = 1e-3 * max(abs(share), 0.05)
        for j, lab in enumerate(labels):
            out[f"{e}.{lab}"] = float(a_m[j])
            out[f"{e}.{lab}.ratio"] = float(np.log10((a_m[j] + eps) / (a_l[j] + eps)))
            out[f"{e}.{lab}.phase"] = (float(_wrap_deg(np.array(p_m0[j] - p_l0[j])))
                                       if a_m[j] > 0 and a_l[j] > 0 else np.nan)
        # harmonics of the channel's dominant baseline mode
        f0 = float(freqs[int(np.argmax(a_l))])
        h_m = harmonic_amplitudes(dyn_m / step, rate, f0, options.harmonics)
        h_l = harmonic_amplitudes(dyn_l / step, rate, f0, options.harmonics)
        for k, hm, hl in zip(options.harmonics, h_m, h_l):
            out[f"{e}.H{k}"] = float(hm - hl)
    else:
        out.update({k: np.nan for k in nan_keys[:len(labels) * 3 + len(options.harmonics)]})
    out[f"{e}.residual"] = float(np.sqrt(np.mean((dyn_m - dyn_l) ** 2)) / abs(step_c))
    # TAF: peak over static (bite), undershoot over the rolling level (release)
    ta = tr.t_step - 0.05
    tb = min(tr.t_step + options.taf_window_s, tr.t_next - 0.05, sig.t_end)
    xw = sig.window(ta, tb)
    lw = lin_at(ta + np.arange(xw.size) / rate)
    if tr.kind is Kind.BITE:
        taf = float(np.max(xw) / post_c) if post_c != 0 else np.nan
        taf_l = float(np.max(lw) / lin_level) if lin_level != 0 else np.nan
    else:
        taf = float(-np.min(xw - post_c) / (pre_c - post_c)) if pre_c != post_c else np.nan
        taf_l = float(-np.min(lw - lin_level) / (pre_c - lin_level)) if pre_c != lin_level \
            else np.nan
    out[f"{e}.taf"] = taf
    out[f"{e}.taf.excess"] = taf - taf_l
    # lag of the channel's own half-height crossing behind the baseline's
    rising = post_c > pre_c
    t_m = half_crossing(sig, tr.t_step, pre_c + 0.5 * (post_c - pre_c), rising, span=0.06)
    tl = tr.t_step - 0.06 + np.arange(int(0.12 * rate)) / rate
    ll = Signal("lin", e, tl[0], rate, lin_at(tl))
    t_l = half_crossing(ll, tr.t_step, pre_c + 0.5 * (lin_level - pre_c), lin_level > pre_c,
                        span=0.059)
    out[f"{e}.lag_ms"] = (1e3 * (t_m - t_l) if (t_m is not None and t_l is not None)
                          else np.nan)
    # dwell near the new level (inside a gap the torque is only the damper's)
    nd = min(int(options.dwell_s * rate), dyn_m.size)
    tol = 0.02 * abs(step_c)
    out[f"{e}.dwell"] = float(np.mean(np.abs(dyn_m[:nd]) < tol) - np.mean(np.abs(dyn_l[:nd]) < tol))
    return out, sw


def _first(mask: np.ndarray) -> int | None:
    i = np.flatnonzero(mask)
    return int(i[0]) if i.size else None


def _accel_features(sig: Signal, tr: Transient, a_ref: float,
                    options: FeatureOptions) -> dict[str, float]:
    k = sig.target
    out: dict[str, float] = {}
    t_a = max(tr.t_step - 0.05, 0.5 * (tr.t_prev + tr.t_step) if np.isfinite(tr.t_prev) else -1)
    t_b = min(tr.t_step + options.bearing_window_s, tr.t_next - 0.05, sig.t_end)
    x = sig.window(t_a, t_b)
    names = ["rms", "peak", "crest", "kurtosis", "f_peak", "centroid_hz", "phase", "rms_late",
             "impact_ms"]
    names += [f"H{h}" for h in options.harmonics]
    names += [f"band{i}" for i in range(len(BAND_EDGES_HZ) - 1)]
    if x.size < 32 or a_ref <= 0:
        return {f"{k}.{n}": np.nan for n in names}
    x = x - np.mean(x)
    rms = float(np.sqrt(np.mean(x ** 2)))
    peak = float(np.max(np.abs(x)))
    # the shaft's flight across its clearance delays the first impact (seed 2.2)
    i_imp = _first(np.abs(x) > 0.3 * peak)
    out[f"{k}.impact_ms"] = (1e3 * ((t_a - tr.t_step) + i_imp / sig.rate_hz)
                             if i_imp is not None else np.nan)
    out[f"{k}.rms"] = float(np.log10(rms / a_ref + 1e-12))
    out[f"{k}.peak"] = float(np.log10(peak / a_ref + 1e-12))
    out[f"{k}.crest"] = peak / rms if rms > 0 else np.nan
    out[f"{k}.kurtosis"] = float(np.mean(x ** 4) / rms ** 4) if rms > 0 else np.nan
    n = x.size
    nfft = int(2 ** np.ceil(np.log2(2 * n)))
    w = np.hanning(n)
    X = np.fft.rfft(x * w, nfft)
    f = np.fft.rfftfreq(nfft, 1.0 / sig.rate_hz)
    P = np.abs(X) ** 2
    band = (f >= 30.0) & (f <= 0.45 * sig.rate_hz)
    if not band.any() or P[band].sum() <= 0:
        return {f"{k}.{n_}": out.get(f"{k}.{n_}", np.nan) for n_ in names}
    ib = np.flatnonzero(band)
    ip = ib[np.argmax(P[ib])]
    fp = float(f[ip])
    out[f"{k}.f_peak"] = fp
    out[f"{k}.centroid_hz"] = float(np.sum(f[band] * P[band]) / np.sum(P[band]))
    tt = (t_a - tr.t_step) + np.arange(n) / sig.rate_hz
    z = np.sum(w * x * np.exp(-2j * np.pi * fp * tt))
    out[f"{k}.phase"] = float(np.degrees(np.angle(z)))
    amp0 = np.abs(z)
    for h in options.harmonics:
        zh = np.sum(w * x * np.exp(-2j * np.pi * h * fp * tt))
        out[f"{k}.H{h}"] = float(np.abs(zh) / amp0) if amp0 > 0 else np.nan
    tot = P[f >= 0].sum()
    for i in range(len(BAND_EDGES_HZ) - 1):
        sel = (f >= BAND_EDGES_HZ[i]) & (f < BAND_EDGES_HZ[i + 1])
        out[f"{k}.band{i}"] = float(P[sel].sum() / tot) if tot > 0 else np.nan
    late = sig.window(tr.t_step + options.bearing_window_s, min(tr.t_step + 0.6, tr.t_next - 0.05))
    out[f"{k}.rms_late"] = (float(np.log10(np.sqrt(np.mean((late - late.mean()) ** 2)) / a_ref
                                           + 1e-12)) if late.size > 16 else np.nan)
    return out


def transient_features(rec: Recording, mill: Mill, t_steps: Sequence[float] | None = None, *,
                       reference: LinearReference | None = None,
                       options: FeatureOptions = FeatureOptions()) -> TransientFeatures:
    """Features of every load-step transient of a recording.

    Parameters
    ----------
    rec : Recording
        SI frames (torques N*m on the physical shaft, accelerations m/s^2).
    mill : Mill
    t_steps : sequence of float, optional
        Approximate step times, s (``ident.segment`` results' ``t_step``); found
        from the torque nearest the rolls when omitted.
    reference : LinearReference, optional
        The mill's baseline responses; pass one instance for many recordings.
    options : FeatureOptions

    Returns
    -------
    TransientFeatures
    """
    reference = reference if reference is not None else LinearReference(mill)
    signals = torque_signals(rec, mill)
    accels = acceleration_signals(rec, mill)
    if t_steps is None:
        t_steps = find_steps(signals, mill)
    T_nom = nominal_torque(mill)
    transients = refine_transients(signals, mill, t_steps, min_step=0.05 * T_nom)
    ref, share_ref = reference_signal(signals, mill)
    near = nearest_load_elements(mill, signals)
    shares = static_shares(mill)
    labels = frequency_labels(reference.modes.frequencies_hz)
    freqs, damping = reference.poles
    base = _Superposed()
    units = []
    for tr in transients:
        pre_ref = tr.static_torque * share_ref if tr.kind is Kind.RELEASE else \
            (tr.static_torque - tr.step) * share_ref
        t_pre = np.arange(max(tr.t_step - 0.25, tr.t_prev + 0.02 if np.isfinite(tr.t_prev)
                              else ref.t0), tr.t_step - 0.04, 1.0 / ref.rate_hz)

        def prior(t: np.ndarray, upto: float = tr.t_step - 1e-6) -> np.ndarray:
            return sum(base.delta(e, t, upto, reference, ref.rate_hz) for e in near)

        anchor = float(np.median(prior(t_pre))) if t_pre.size and base.steps else 0.0
        unit, shift = reference.fit_rise(ref, tr.t_step, pre_ref, tr.step, share_ref, near,
                                         background=(lambda t: prior(t) - anchor)
                                         if base.steps else None)
        base.add(tr.t_step + shift, tr.step, unit)
        units.append(unit)
    filtered = {e: lowpass(sig.x, sig.rate_hz, options.lowpass_hz) for e, sig in signals.items()}
    near_f = sum(filtered[e] for e in near) if len(near) > 1 else None
    n_pre = int(round(options.sweep_before_s * ref.rate_hz))
    rows = []
    kept = []
    with threadpool_limits(1):
        for tr, unit in zip(transients, units):
            if tr.t_next - tr.t_step < options.min_window_s:
                continue
            static_norm = tr.static_torque / T_nom
            i_tr = transients.index(tr)
            after_release = i_tr > 0 and transients[i_tr - 1].kind is Kind.RELEASE
            row: dict[str, Any] = {"t_step": tr.t_step, "kind": tr.kind.value,
                                   "static_torque": tr.static_torque, "step": tr.step,
                                   "rise_s": unit.rise_s, "after_release": after_release,
                                   "static": static_norm, "rise_ms": 1e3 * unit.rise_s}
            # the load between bars (before a bite, after a release): with any, the
            # gaps close on their drive side during the pause
            lo, hi = ((tr.t_step - 0.25, tr.t_step - 0.04) if tr.kind is Kind.BITE else
                      (tr.t_step + 0.25, min(tr.t_step + 0.6, tr.t_next - 0.05)))
            w = ref.window(lo, hi)
            row["idle_level"] = (float(np.median(w)) / (share_ref * T_nom) if w.size
                                 else np.nan)
            sweeps = {}
            for e, sig in signals.items():
                f, sw = _torque_channel_features(sig, filtered[e], tr, base, reference,
                                                 rise_s=unit.rise_s, share=shares[e],
                                                 static_norm=static_norm, labels=labels,
                                                 freqs=freqs, damping=damping,
                                                 options=options)
                row.update(f)
                sweeps[e] = sw
            if near_f is not None:
                pre_n, _ = _levels(Signal("near", "near", ref.t0, ref.rate_hz, near_f),
                                   tr.t_step, tr.t_prev, tr.t_next)
                y = normalised_window(near_f, ref.t0, ref.rate_hz, tr.t_step, pre_n,
                                      tr.step * share_ref, before_s=options.sweep_before_s,
                                      after_s=options.sweep_after_s)
                sw = sweep_features(y, ref.rate_hz, n_pre, static_norm,
                                    tr.t_next - 0.05 - tr.t_step)
                row.update({f"near.{k}": v for k, v in sw.items()})
            row.update(pair_differences(sweeps, static_norm))
            for key, sig in accels.items():
                b = mill.bearing(key.split(":")[0])
                f_step = abs(tr.step * shares[b.mesh]) * b.ratio / b.base_radius
                a_ref = f_step / b.housing_mass
                row.update(_accel_features(sig, tr, a_ref, options))
                for wname, (wa, wb) in WINDOWS.items():
                    t_b = min(tr.t_step + wb, tr.t_next - 0.05, sig.t_end)
                    x = sig.window(tr.t_step + wa, t_b)
                    row.update({f"{key}.{wname}.{k}": v
                                for k, v in rattle_features(x, sig.rate_hz, a_ref).items()})
            rows.append(row)
            kept.append(tr)
    table = pd.DataFrame(rows)
    return TransientFeatures(transients=tuple(kept), table=table,
                             frequencies_hz=np.asarray(reference.modes.frequencies_hz, float),
                             ringing_hz=freqs, ringing_damping=damping,
                             channels=tuple(signals), accelerometers=tuple(accels),
                             nominal_torque=T_nom)


_META = ("t_step", "kind", "static_torque", "step", "rise_s", "after_release")
#: per-transient features also aggregated by their largest value over the recording
_MAX_OF = ("lag_ms", "taf", "residual", "impact_ms")


def _is_sweep(column: str) -> bool:
    """A channel's (not a pair's) gap-sweep feature."""
    where, _, name = column.partition(".")
    return name in SWEEP_FEATURES and "-" not in where


def recording_features(tf: TransientFeatures) -> pd.Series:
    """One recording's feature vector: medians per kind and the TAF-static relation.

    The bites aggregated are those that follow a release in the recording
    when there are any: the release's rebound and the speed loop's braking
    leave every element on its back flank, so the next bite sweeps whole
    gaps, while the recording's first bite finds only their unknown open
    parts (``gap_open``).

    Returns
    -------
    Series
        ``bite.{feature}`` and ``release.{feature}`` medians over the
        transients of that kind (NaN when there is none); for the channels'
        gap-sweep features also ``.min`` and ``.max`` over them (the gap is
        swept wider at some steps than at others), for ``lag_ms``, ``taf``,
        ``residual`` and ``impact_ms`` also ``.max``; ``bite.{E}.taf_slope``
        (change of TAF per unit of static torque / nominal torque, seed 1.1;
        NaN with fewer than two bites or static torques within 10 % of the
        nominal of each other), ``bite.static`` (median static torque over
        the nominal) and ``n_bites``/``n_releases``.
    """
    t = tf.table
    feats = [c for c in t.columns if c not in _META]
    out: dict[str, float] = {}
    kinds = t["kind"].to_numpy() if len(t) else np.array([])
    swept = (t["after_release"].to_numpy(dtype=bool) if "after_release" in t
             else np.ones(len(t), bool)) if len(t) else np.array([], bool)
    for kind in (Kind.BITE.value, Kind.RELEASE.value):
        sel = kinds == kind
        if kind == Kind.BITE.value and (sel & swept).any():
            sel = sel & swept
        sub = t.loc[sel, feats].to_numpy(dtype=float) if len(t) else \
            np.empty((0, len(feats)))
        ok = np.isfinite(sub).any(axis=0) if sub.shape[0] else np.zeros(len(feats), bool)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.where(ok, np.nanmedian(sub, axis=0), np.nan) if sub.shape[0] else \
                np.full(len(feats), np.nan)
            mx = np.where(ok, np.nanmax(np.where(np.isfinite(sub), sub, -np.inf), axis=0),
                          np.nan) if sub.shape[0] else np.full(len(feats), np.nan)
            mn = np.where(ok, np.nanmin(np.where(np.isfinite(sub), sub, np.inf), axis=0),
                          np.nan) if sub.shape[0] else np.full(len(feats), np.nan)
        for i, c in enumerate(feats):
            out[f"{kind}.{c}"] = float(med[i])
            sweep = _is_sweep(c)
            if sweep or c.rsplit(".", 1)[-1] in _MAX_OF or c.endswith("taf.excess"):
                out[f"{kind}.{c}.max"] = float(mx[i])
            if sweep:
                out[f"{kind}.{c}.min"] = float(mn[i])
    bites = t[t["kind"] == Kind.BITE.value] if len(t) else t
    s = bites["static_torque"].to_numpy(dtype=float) / tf.nominal_torque if len(bites) else \
        np.array([])
    out["bite.static"] = float(np.median(s)) if s.size else np.nan
    for e in tf.channels:
        slope = np.nan
        if s.size >= 2 and np.ptp(s) >= 0.1:
            y = bites[f"{e}.taf"].to_numpy(dtype=float)
            ok = np.isfinite(y)
            if ok.sum() >= 2 and np.ptp(s[ok]) >= 0.1:
                slope = float(np.polyfit(s[ok], y[ok], 1)[0])
        out[f"bite.{e}.taf_slope"] = slope
    out["n_bites"] = float(len(bites))
    out["n_releases"] = float(len(t) - len(bites)) if len(t) else 0.0
    return pd.Series(out, dtype=float)


def feature_summary(tf: TransientFeatures, element_id: str | None = None, *,
                    mill: Mill | None = None) -> dict[str, list[float]]:
    """The ``features`` block of ``ident diagnose`` (cli.md).

    Median over the bites of the amplitude ratio (linear, measured over
    baseline) and the phase shift (deg) at each natural frequency, in the
    channel nearest the rolls of ``mill`` unless ``element_id`` names another
    (without ``mill``: the first channel).

    Returns
    -------
    dict
        ``frequencies_hz``, ``amplitude_ratio``, ``phase_shift_deg``,
        ``channel`` (the element id).
    """
    labels = frequency_labels(tf.frequencies_hz)
    t = tf.table
    bites = t[t["kind"] == Kind.BITE.value] if len(t) else t
    if len(bites) == 0:
        bites = t
    if element_id is None:
        near = nearest_load_elements(mill, tf.channels) if mill is not None and tf.channels \
            else tf.channels
        element_id = near[0] if near else ""
    ratio, phase = [], []
    for lab in labels:
        col = f"{element_id}.{lab}"
        if len(bites) and f"{col}.ratio" in bites:
            ratio.append(float(10 ** np.nanmedian(bites[f"{col}.ratio"])))
            ph = bites[f"{col}.phase"].to_numpy(dtype=float)
            phase.append(float(np.nanmedian(ph)) if np.isfinite(ph).any() else float("nan"))
        else:
            ratio.append(float("nan"))
            phase.append(float("nan"))
    return {"frequencies_hz": [float(f) for f in tf.frequencies_hz], "amplitude_ratio": ratio,
            "phase_shift_deg": phase, "channel": element_id}
