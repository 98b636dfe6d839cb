"""Synthetic rolling-mill telemetry with known truth, for the io and segment tests.

Stands in for ``ident.model.simulate`` (written in parallel) with a kinematic model
that has what the segmenter must cope with:

* bars: a bite (load step up) and a release (step down), each a raised-cosine ramp
  of 10-40 ms centred on its true ``t_step`` (half height), the static rolling torque
  varying from bar to bar (250-500 kN*m total, reduced to the motor shaft);
* the load shares of the mill description on each torque channel (element ``ratio``
  to the physical shaft), damped oscillations at the stand's natural frequencies
  (12-81 Hz, 2-4 % damping, torque amplification up to ~1.5) starting when each ramp
  ends;
* load fluctuation while rolling (+-2 %), slow offset drift of each sensor (~1 % of
  its level), white noise at 30-40 dB below the channel's rolling level, 16-bit
  quantisation, short pauses between bars and a long idle stretch with noise only;
* accelerometers (g) on the bearing housings: a gear-mesh tone whose amplitude
  follows the mesh torque, a housing-resonance burst at every step, noise.

Truth times are seconds from the recording's start (the first sample).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ident.description import Mill
from ident.io.recording import RawDevice

T0_NS = 1_732_252_800_000_000_000  # 2024-11-22T05:20:00Z
MODES_HZ = (12.0, 15.0, 20.0, 34.0, 45.0, 81.0)


@dataclass(frozen=True)
class TruthStep:
    kind: str          # "bite" | "release"
    t_step: float      # s from the recording start, half height
    rise_s: float      # ramp duration, s
    static: float      # rolling level of the bar, N*m total reduced to the motor shaft
    step: float        # change, N*m total reduced (negative for a release)


@dataclass(frozen=True)
class Synth:
    devices: tuple[RawDevice, ...]
    truth: tuple[TruthStep, ...]
    idle: tuple[tuple[float, float], ...]   # stretches with noise only, s
    duration_s: float

    def device(self, quantity: str) -> RawDevice:
        return self.devices[0] if quantity == "torque" else self.devices[1]


def load_fractions(mill: Mill) -> dict[str, float]:
    """Static share of the rolling torque per element (tree: shares on its `to` side)."""
    adj: dict[str, list[tuple[str, str]]] = {m.id: [] for m in mill.masses}
    for e in mill.elements:
        adj[e.from_].append((e.to, e.id))
        adj[e.to].append((e.from_, e.id))
    share = dict(zip(mill.load.masses, mill.load.share))
    out = {}
    for e in mill.elements:
        seen = {e.from_}
        stack = [e.to]
        tot = 0.0
        while stack:
            m = stack.pop()
            if m in seen:
                continue
            seen.add(m)
            tot += share.get(m, 0.0)
            stack += [n for n, eid in adj[m] if eid != e.id]
        out[e.id] = tot
    return out


def _ramp(tau: np.ndarray, rise: float) -> np.ndarray:
    """Raised cosine from 0 to 1 over [-rise/2, rise/2]."""
    x = np.clip(tau / rise, -0.5, 0.5)
    return 0.5 * (1.0 + np.sin(np.pi * x))


def _quantise(x: np.ndarray, full_scale: float) -> np.ndarray:
    lsb = 2.0 * full_scale / 65536.0
    return (np.clip(np.round(x / lsb), -32768, 32767) * lsb).astype(np.float32)


def make_synth(mill: Mill, *, seed: int, duration_s: float = 45.0, torque_rate_hz: float = 2000.0,
               accel_rate_hz: float = 10000.0, with_torque: bool = True,
               with_accel: bool = True, idle_s: float = 8.0, snr_db: tuple[float, float] = (30, 40),
               t0_ns: int = T0_NS) -> Synth:
    """Generate a recording of several bars with known bite/release times.

    Returns devices ``/telemetry/torque`` (the mill's torque channels, kN*m) and
    ``/telemetry/accel`` (its acceleration channels, g).
    """
    rng = np.random.default_rng(seed)
    # ---- timeline -----------------------------------------------------------------------
    bars: list[tuple[float, float, float, float, float]] = []  # bite, release, static, r1, r2
    t = rng.uniform(1.5, 2.5)
    idle_stretches = [(0.0, t - 0.1)]
    idle_done = False
    while True:
        length = rng.uniform(2.0, 5.0)
        if t + length + 1.5 > duration_s:
            break
        static = rng.uniform(250e3, 500e3)
        bars.append((t, t + length, static, rng.uniform(0.010, 0.040), rng.uniform(0.010, 0.040)))
        t += length
        if not idle_done and t > duration_s / 3:
            # after the release ring-down, before the next bite
            idle_stretches.append((t + 1.2, t + idle_s - 0.2))
            t += idle_s
            idle_done = True
        else:
            t += rng.uniform(0.4, 2.5)  # short pause between bars
    truth = []
    for bite, release, static, r1, r2 in bars:
        truth.append(TruthStep("bite", bite, r1, static, static))
        truth.append(TruthStep("release", release, r2, static, -static))

    def load(tt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Total load (N*m reduced) and the oscillation 'unit' response per mode."""
        L = np.zeros_like(tt)
        for bite, release, static, r1, r2 in bars:
            a0, a1, b0, b1 = np.searchsorted(tt, [bite - r1 / 2, bite + r1 / 2,
                                                  release - r2 / 2, release + r2 / 2])
            L[a0:a1] += static * _ramp(tt[a0:a1] - bite, r1)
            L[a1:b0] += static
            L[b0:b1] += static * (1.0 - _ramp(tt[b0:b1] - release, r2))
        fl = np.zeros_like(tt)
        for _ in range(3):
            fl += rng.uniform(0.003, 0.007) * np.sin(2 * np.pi * rng.uniform(0.2, 1.5) * tt
                                                     + rng.uniform(0, 2 * np.pi))
        return L * (1.0 + fl), fl

    fractions = load_fractions(mill)
    devices = []
    # ---- torque device ------------------------------------------------------------------
    osc_amp = {e.id: rng.uniform(0.05, 0.12, size=len(MODES_HZ)) for e in mill.elements}
    zeta = rng.uniform(0.02, 0.04, size=len(MODES_HZ))

    def oscillation(tt: np.ndarray, element: str) -> np.ndarray:
        out = np.zeros_like(tt)
        for s in truth:
            t_on = s.t_step + s.rise_s / 2
            i0, i1 = np.searchsorted(tt, [t_on, t_on + 3.0])
            tau = tt[i0:i1] - t_on
            for j, f in enumerate(MODES_HZ):
                w = 2 * np.pi * f
                out[i0:i1] += (osc_amp[element][j] * s.step * np.exp(-zeta[j] * w * tau)
                               * np.sin(w * tau))
        return out

    n_t = int(round(duration_s * torque_rate_hz))
    tt = np.arange(n_t) / torque_rate_hz
    L, _ = load(tt)
    if with_torque:
        chans, rows = [], []
        for ch in mill.torque_channels():
            e = mill.element(ch.element)
            frac = fractions[e.id]
            nominal = e.ratio * frac * 375e3
            x = e.ratio * frac * (L + oscillation(tt, e.id))
            drift = 0.01 * nominal * (np.sin(2 * np.pi * tt / rng.uniform(30, 120)
                                             + rng.uniform(0, 2 * np.pi))
                                      + rng.uniform(-0.5, 0.5))
            sigma = nominal * 10 ** (-rng.uniform(*snr_db) / 20)
            x = x + drift + rng.normal(0.0, sigma, size=n_t)
            rows.append(_quantise(x / 1e3, 2.5 * e.ratio * frac * 500e3 / 1e3))
            chans.append(ch.name)
        devices.append(RawDevice("/telemetry/torque", torque_rate_hz, t0_ns, tuple(chans),
                                 ("kN*m",) * len(chans), np.vstack(rows)))
    # ---- accelerometers ---------------------------------------------------------------------
    if with_accel and mill.acceleration_channels():
        n_a = int(round(duration_s * accel_rate_hz))
        ta = np.arange(n_a) / accel_rate_hz
        La, _ = load(ta)
        chans, rows = [], []
        mesh_osc: dict[str, np.ndarray] = {}
        for k, ch in enumerate(mill.acceleration_channels()):
            b = mill.bearing(ch.bearing)
            frac = fractions[b.mesh]
            if b.mesh not in mesh_osc:
                mesh_osc[b.mesh] = oscillation(ta, b.mesh)
            mesh = frac * (La + mesh_osc[b.mesh])
            f_mesh = 420.0 if k < 2 else 240.0
            amp = 0.02 + 0.3 * np.abs(mesh) / (frac * 375e3)
            phi = 0.0 if ch.direction == "vertical" else np.pi / 2
            x = amp * np.sin(2 * np.pi * f_mesh * ta + phi)
            for s in truth:
                i0, i1 = np.searchsorted(ta, [s.t_step, s.t_step + 0.3])
                tau = ta[i0:i1] - s.t_step
                x[i0:i1] += 0.4 * abs(s.step) / 375e3 * np.exp(-tau / 0.03) * np.sin(
                    2 * np.pi * 1100.0 * tau)
            x += rng.normal(0.0, rng.uniform(0.01, 0.02), size=n_a)
            rows.append(_quantise(x, 5.0))
            chans.append(ch.name)
        devices.append(RawDevice("/telemetry/accel", accel_rate_hz, t0_ns, tuple(chans),
                                 ("g",) * len(chans), np.vstack(rows)))
    return Synth(tuple(devices), tuple(truth), tuple(idle_stretches), duration_s)
