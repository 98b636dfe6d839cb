"""Simulate the nonlinear driveline through a rolling scenario, and its sensors.

:func:`simulate` integrates the model of ``ident.model.dynamics`` (exact g1
kinks by default) with the compiled fixed-step RK4 of
``ident.model.integrate``; :func:`sensor_devices` turns the result into what the
telemetry would record (physical torques through each element's ratio,
housing accelerations, sensor noise at a given SNR, 16-bit quantisation);
:func:`taf_table` gives peak torque and torque amplification factor (TAF) per
element and bar (seed section 1.1, Fig. 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from ..description import Mill, Quantity
from ..io.recording import RawDevice
from ..units import to_si_factor
from .dynamics import Driveline, ModelOptions, build_driveline
from .integrate import integrate, make_stepper, stage_times
from .scenario import Scenario, load_profile

__all__ = ["SimResult", "simulate", "sensor_devices", "taf_table", "DEFAULT_T0_NS",
           "TORQUE_DEVICE", "ACCEL_DEVICE"]

#: 2026-01-01T00:00:00Z, the default absolute start of simulated recordings.
DEFAULT_T0_NS = 1_767_225_600_000_000_000
TORQUE_DEVICE = "/telemetry/torque"
ACCEL_DEVICE = "/telemetry/accel"


@dataclass(frozen=True)
class SimResult:
    """A simulated transient record (noise-free truth).

    Attributes
    ----------
    mill : Mill
    scenario : Scenario
    driveline : Driveline
    params : ndarray
        Parameter vector used (``driveline.param_names``).
    outputs : DataFrame
        Index ``time_s``; columns ``driveline.output_names`` (reduced element
        torques ``tau:ID`` in N*m, ``T_motor``, ``T_load``, bearing signals).
    states : DataFrame
        Index ``time_s``; columns ``driveline.state_names``.
    rate_hz : float
        Sample rate of ``outputs`` and ``states``.
    """

    mill: Mill
    scenario: Scenario
    driveline: Driveline
    params: np.ndarray
    outputs: pd.DataFrame
    states: pd.DataFrame
    rate_hz: float
    meta: Mapping[str, float] = field(default_factory=dict)

    @property
    def time(self) -> np.ndarray:
        return self.outputs.index.to_numpy()

    def torque(self, element_id: str, *, physical: bool = False) -> pd.Series:
        """Torque transmitted by an element, N*m (reduced, or physical with ``ratio``)."""
        s = self.outputs[f"tau:{element_id}"]
        return s * self.mill.element(element_id).ratio if physical else s


def simulate(mill: Mill, scenario: Scenario, *, options: ModelOptions | None = None,
             params: Mapping[str, float] | None = None, rate_hz: float | None = None,
             max_step: float = 5e-5, x0: np.ndarray | None = None,
             compile: bool = True) -> SimResult:
    """Simulate the driveline of ``mill`` through ``scenario``.

    Parameters
    ----------
    mill : Mill
    scenario : Scenario
    options : ModelOptions, optional
        Defaults to exact g1 laws, with the bearings' radial model when the mill
        has bearings.
    params : mapping, optional
        Overrides of model parameters by name (``"C46.gap"``, effect parameters).
    rate_hz : float, optional
        Output sample rate; default 10 kHz with bearings, else 2 kHz.
    max_step : float
        Largest RK4 step, s (5e-5 s passes the step-halving test for g1).
    x0 : ndarray, optional
        Initial state (default: at rest, gaps as the mill file says).
    compile : bool
        Compile the integrator to C (see ``ident.model.integrate``).

    Returns
    -------
    SimResult
    """
    if options is None:
        options = ModelOptions(bearings=bool(mill.bearings))
    drv = build_driveline(mill, options)
    if rate_hz is None:
        rate_hz = 10_000.0 if (options.bearings and mill.bearings) else 2_000.0
    T = 1.0 / rate_hz
    n_sub = max(1, math.ceil(T / max_step - 1e-9))
    stepper = make_stepper(drv, interval=T, n_sub=n_sub, compile=compile, stage_inputs=True)
    N = int(round(scenario.duration * rate_hz)) + 1
    t = np.arange(N) * T
    u = load_profile(scenario, t)
    u_stages = load_profile(scenario, stage_times(stepper, N)).reshape(N - 1, -1)
    p = drv.params(dict(params or {}))
    x_start = drv.x_idle.copy() if x0 is None else np.asarray(x0, dtype=float)
    X, Y_end = integrate(stepper, x_start, u_stages, p, 0.0)
    y0 = np.asarray(drv.out(x_start, u[:1], p, 0.0)).ravel()
    Y = np.vstack([y0[None, :], Y_end])
    idx = pd.Index(t, name="time_s")
    return SimResult(mill=mill, scenario=scenario, driveline=drv, params=p,
                     outputs=pd.DataFrame(Y, index=idx, columns=list(drv.output_names)),
                     states=pd.DataFrame(X, index=idx, columns=list(drv.state_names)),
                     rate_hz=rate_hz, meta={"n_sub": n_sub, "compiled": stepper.compiled})


def _quantise(x: np.ndarray, bits: int) -> tuple[np.ndarray, float]:
    """Quantise to ``bits`` over a full scale of 1.25*max|x| rounded up to 1-2-5."""
    peak = float(np.nanmax(np.abs(x))) if x.size else 1.0
    peak = max(peak * 1.25, 1e-12)
    mag = 10 ** math.floor(math.log10(peak))
    fs = next(m * mag for m in (1, 2, 5, 10) if m * mag >= peak)
    lsb = 2 * fs / 2 ** bits
    return np.clip(np.round(x / lsb) * lsb, -fs, fs - lsb), fs


def sensor_devices(result: SimResult, *, rng: np.random.Generator, snr_db: float = 35.0,
                   bits: int = 16, torque_rate_hz: float = 2_000.0,
                   accel_rate_hz: float = 10_000.0, t0_ns: int = DEFAULT_T0_NS,
                   channels: Sequence[str] | None = None) -> tuple[RawDevice, ...]:
    """What the telemetry records of a simulation, per the mill's sensor map.

    Torque channels read the element's physical torque (reduced torque times
    ``ratio``), speed channels the mass's absolute speed, acceleration channels
    the bearing housing's acceleration in their direction.  Each channel gets
    white noise at ``snr_db`` below its RMS, is quantised to ``bits`` over a
    full scale of 1.25 times its peak, and is written in its unit through the
    channel's scale and offset.  Torque and speed channels form the strain
    telemetry device (``torque_rate_hz``), accelerations the accelerometer
    device (``accel_rate_hz``); rates must divide the simulation rate.

    Returns
    -------
    tuple of RawDevice
    """
    mill = result.mill
    out = result.outputs
    names = set(channels) if channels is not None else None
    groups: dict[str, list[tuple[str, str, np.ndarray]]] = {TORQUE_DEVICE: [], ACCEL_DEVICE: []}
    for ch in mill.channels:
        if names is not None and ch.name not in names:
            continue
        if ch.quantity is Quantity.TORQUE:
            e = mill.element(ch.element)
            si = out[f"tau:{e.id}"].to_numpy() * e.ratio
            dev, rate = TORQUE_DEVICE, torque_rate_hz
        elif ch.quantity is Quantity.SPEED:
            si = result.states[f"omega:{ch.mass}"].to_numpy() + mill.motor_speed
            dev, rate = TORQUE_DEVICE, torque_rate_hz
        else:
            key = f"acc:{ch.bearing}:{'v' if ch.direction == 'vertical' else 'h'}"
            if key not in out.columns:
                continue  # bearings not simulated
            si = out[key].to_numpy()
            dev, rate = ACCEL_DEVICE, accel_rate_hz
        q = result.rate_hz / rate
        if abs(q - round(q)) > 1e-9 or round(q) < 1:
            raise ValueError(f"channel rate {rate} Hz must divide the simulation rate "
                             f"{result.rate_hz} Hz")
        x = si[::int(round(q))]
        rms = float(np.sqrt(np.mean(x ** 2))) if x.size else 0.0
        x = x + rng.normal(0.0, rms * 10 ** (-snr_db / 20.0) if rms > 0 else 0.0, x.size)
        x = x / to_si_factor(ch.quantity.value, ch.unit)
        x, _ = _quantise(x, bits)
        rec = (x - ch.offset) / ch.scale
        groups[dev].append((ch.name, ch.unit, rec))
    devices = []
    for dev, rate in ((TORQUE_DEVICE, torque_rate_hz), (ACCEL_DEVICE, accel_rate_hz)):
        g = groups[dev]
        if not g:
            continue
        n = min(len(v) for _, _, v in g)
        devices.append(RawDevice(name=dev, rate_hz=rate, t0_ns=t0_ns,
                                 channels=tuple(c for c, _, _ in g),
                                 units=tuple(u for _, u, _ in g),
                                 data=np.stack([v[:n] for _, _, v in g]).astype(np.float64)))
    return tuple(devices)


def taf_table(result: SimResult, *, window_s: float = 1.0) -> pd.DataFrame:
    """Peak torque and TAF per bar and element at each bite (seed section 1.1, Fig. 3).

    The static torque is the element's median torque over the last half of
    the bar's rolling time; the peak is the largest torque within ``window_s``
    after the bite; ``taf = peak / static``.

    Returns
    -------
    DataFrame
        Columns ``bar, element, static_torque, peak_torque, taf`` (N*m reduced).
    """
    rows = []
    t = result.time
    for ib, bar in enumerate(result.scenario.bars):
        roll_end = bar.t_release
        roll_start = bar.t_bite + bar.rise_time
        late = (t >= roll_start + 0.5 * (roll_end - roll_start)) & (t < roll_end)
        win = (t >= bar.t_bite) & (t < min(bar.t_bite + window_s, roll_end))
        for e in result.mill.elements:
            tau = result.outputs[f"tau:{e.id}"].to_numpy()
            static = float(np.median(tau[late])) if late.any() else float("nan")
            peak = float(np.max(tau[win])) if win.any() else float("nan")
            rows.append({"bar": ib, "element": e.id, "static_torque": static,
                         "peak_torque": peak,
                         "taf": peak / static if static and abs(static) > 0 else float("nan")})
    return pd.DataFrame(rows)
