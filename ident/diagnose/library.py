"""A library of simulated recordings over wear states and nuisance variation.

The classifier learns from recordings simulated from the mill file: every
sample draws, independently,

* the elements' gaps: a number of *faulty* elements (``LibraryRanges.faults``:
  none, one, two or three, most often one or two) picked at random, each worn
  or critical with equal odds (uniform inside the class, critical up to
  ``critical_span`` times the critical limit); every other element good
  (uniform in ``[0, gap_worn]``); each open part ``gap_open`` uniform in
  ``[0, gap]``.  Wear is local: a stand with all its couplings worn at once is
  not one that is rolling, and with four torque channels on six elements in
  series and in parallel, several wide gaps on one load path are not told
  apart by any transient feature (``notebooks/02_features.ipynb`` measures
  how the accuracy falls as faults pile up);
* each bearing's radial clearance, class-balanced against its limits;
* nuisance: every element's stiffness (+-10 %) and damping (+-30 %), the
  bearings' stiffnesses (+-10 %), damping (+-30 %) and housing preload
  (+-20 %), the bars' number, static torques, rise times, rolling and idle
  times, the idle load, the load fluctuation and the sensors' SNR;
* in half the samples (``LibraryRanges.drag_fraction``) a bearing-friction drag
  on the masses upstream of the spindles (:class:`IdleDrag`), which holds the
  couplings and meshes on their drive flanks between bars as a real stand's
  friction does.  It also loads the gear bearings between bars: the mesh
  force of the friction torque lifts part of the shaft's weight off the
  bottom of its clearance (or all of it: the shaft then rests on the top), so
  that after a release the shaft falls more slowly and hits the housing more
  softly than with nothing between bars.  The independent plant simulator's
  friction lifts 0.2-1.3 of the weight of cold-s5's B23 and 0.5-3.3 of
  hsm-f1's; a library without drag read its clearances 0.27 mm small on
  average and called critical bearings worn, worn ones good
  (``validation/diagnose_study.py``);

simulates the torsion with one compiled integrator per process
(:class:`LibrarySimulator`: the stiffness and damping nuisance enter as model
parameters through :class:`Nuisance`), the bearings' radial models driven by
their mesh torques (:mod:`ident.diagnose.radial`), the sensors
(:func:`ident.model.simulate.sensor_devices`: noise, 16-bit quantisation, the
mill's channel map), and extracts the features (:mod:`ident.features`) exactly
as ``ident diagnose`` does for a file.

Cost (measured on one core): about 0.35 s per recording of 6-8 bars with the
bearings, a third of it the torsion, a third the features; with 2-8 bars, half
of the samples with the drag's longer pauses, a 300-sample library and its
model take about 140 s for hsm-f1 and 90 s for cold-s5 (``ident train``).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator

import casadi as ca
import numpy as np
import pandas as pd

from ..description import Mill
from ..features.baseline import LinearReference
from ..features.extract import FeatureOptions, recording_features, transient_features
from ..features.transients import nearest_load_elements
from ..io.recording import Recording, RawDevice
from ..model import laws
from ..model.dynamics import EffectTerms, ModelOptions
from ..model.dynamics import build_driveline
from ..model.integrate import integrate, make_stepper, stage_times
from ..model.scenario import Scenario, load_profile, nominal_torque, random_scenario
from ..model.simulate import SimResult, sensor_devices
from ..units import to_si_factor
from .radial import simulate_radial
from .states import bearing_state, element_state

__all__ = ["Nuisance", "IdleDrag", "drag_masses", "LibraryRanges", "SampleSpec", "Library",
           "LibrarySimulator", "draw_sample", "simulate_sample", "recording_from_devices",
           "simulate_library", "sample_features"]


@dataclass(frozen=True)
class Nuisance:
    """Model effect: each element's stiffness and damping off the mill file's values.

    Parameters per element (prefixed ``nuisance@mill.{ID}.``): ``dk`` (relative
    stiffness change, 1), ``dc`` (added damping, N*m*s/rad), and copies of the
    element's ``gap``/``gap_open`` (rad) that place the added stiffness behind
    the same contact points (set them equal to the element's own).  The extra
    torque ``dk*k*g1(delta; a, b, 1, 0, 1) + dc*delta'`` makes the element's
    law that of stiffness ``k*(1 + dk)`` and damping ``c + dc``.
    """

    element_ids: tuple[str, ...]
    name: str = "nuisance"
    location: str = "mill"

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(f"{e}.{k}" for e in self.element_ids for k in ("dk", "dc", "gap", "gap_open"))

    @property
    def param_defaults(self) -> tuple[float, ...]:
        return tuple(0.0 for _ in self.param_names)

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        out = {}
        for i, eid in enumerate(self.element_ids):
            dk, dc, gap, b = p[4 * i], p[4 * i + 1], p[4 * i + 2], p[4 * i + 3]
            j = ctx.mill.element_ids.index(eid)
            contact = laws.g1(ctx.delta[j], gap - b, b, 1.0, 0.0, 1.0, xp=ca)
            out[j] = dk * ctx.mill.element(eid).k * contact + dc * ctx.ddelta[j]
        return EffectTerms(element_torque=out)

    def params(self, mill: Mill, gaps: dict[str, float], gap_open: dict[str, float],
               k_scale: dict[str, float], c_scale: dict[str, float]) -> dict[str, float]:
        """Parameter values for given gaps and stiffness/damping factors."""
        out = {}
        for e in self.element_ids:
            el = mill.element(e)
            pre = f"{self.name}@{self.location}.{e}"
            out[f"{pre}.dk"] = k_scale[e] - 1.0
            out[f"{pre}.dc"] = (c_scale[e] - 1.0) * el.c
            out[f"{pre}.gap"] = gaps[e]
            out[f"{pre}.gap_open"] = gap_open[e]
        return out


@dataclass(frozen=True)
class IdleDrag:
    """Model effect: a constant drag (bearing friction) opposing rotation on some masses.

    Parameters (prefixed ``drag@mill.{ID}.``): ``torque`` per mass, N*m reduced,
    > 0 opposing the rotation.  On the masses upstream of the spindles it keeps the
    couplings, meshes and shafts on their drive flanks between bars while the
    spindles float in their clearance -- as a rolling mill's bearings and seals do,
    and as :mod:`validation.plantsim` models a stand (its "idle friction").  A bite
    then shows nothing of those gaps; a release, whose ringing reverses the torque,
    still does.
    """

    mass_ids: tuple[str, ...]
    name: str = "drag"
    location: str = "mill"

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(f"{m}.torque" for m in self.mass_ids)

    @property
    def param_defaults(self) -> tuple[float, ...]:
        return tuple(0.0 for _ in self.param_names)

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        ids = [m.id for m in ctx.mill.masses]
        rows = [0.0] * len(ids)
        for i, mid in enumerate(self.mass_ids):
            rows[ids.index(mid)] = -p[i]
        return EffectTerms(mass_torque=ca.vertcat(*rows))

    def params(self, drag: dict[str, float]) -> dict[str, float]:
        """Parameter values of per-mass drags (N*m; masses not named drag nothing)."""
        return {f"{self.name}@{self.location}.{m}.torque": float(drag.get(m, 0.0))
                for m in self.mass_ids}


def drag_masses(mill: Mill) -> tuple[str, ...]:
    """Masses that bearing friction drags: all but the load masses (the roll stacks)."""
    load = set(mill.load.masses)
    return tuple(m.id for m in mill.masses if m.id not in load)


@dataclass(frozen=True)
class LibraryRanges:
    """Ranges of the library's random draws.

    Attributes
    ----------
    faults : tuple of float
        Probabilities of 0, 1, 2, ... faulty (worn or critical) elements per
        recording; the rest are good.
    critical_span : float
        Largest drawn gap (clearance) over the critical limit.
    min_clearance : float
        Smallest drawn bearing clearance, m.
    n_bars : (int, int)
        Bars per recording (inclusive range): from two, as short a recording
        as a diagnosis is asked of, so that the regressors learn how much less
        the medians of few transients say (the rattle after a release is
        chaotic, one bar's features scatter).
    torque : (float, float)
        Static torque over the nominal (``ident.model.scenario.nominal_torque``).
    rise_s, rolling_s, idle_s : (float, float)
        Ramp, rolling and pause durations, s.  The ramps from 5 to 80 ms, as a
        stand's bites and releases take (the fitted rise times of the plant
        simulator's recordings reach 64 ms; the hit windows of the bearings
        see the shaft thrown harder by a faster ramp).
    lead_s : float
        Idle time before the first bite, s.
    idle_load : (float, float)
        Load between bars over the nominal, drawn in a fraction ``idle_fraction``
        of the samples (zero otherwise: gaps then stay open between bars).
    idle_fraction : float
    fluctuation : (float, float)
        Relative load fluctuation while rolling.
    snr_db : (float, float)
        Sensor SNR, dB.
    stiffness, damping : float
        Relative half-ranges of the elements' (and bearings') stiffness and damping.
    preload : float
        Relative half-range of the housing preload.
    drag : (float, float)
        Total idle drag (bearing friction, :class:`IdleDrag`) over the nominal
        torque, drawn in a fraction ``drag_fraction`` of the samples and spread
        over :func:`drag_masses` by weights uniform on the simplex (any share
        on any mass: the gearbox's and the spindles' bearings as much as the
        motor's), so that the load between bars on each gear mesh, and the
        part of its shaft's weight that load lifts, spans 0 to a few times the
        shaft's weight (the nominal torque's mesh force is 20-40 times it).  It is
        drawn from each sample's own seed, so that the other draws of a library
        do not depend on it.
    drag_fraction : float
        Share of the samples with a drag (0.5: as many stands with a load
        between bars as without).
    drag_lead_s, drag_idle_s : float
        Extra idle time before the first bite and before every later one of a
        sample with a drag, s (the simulation starts at rest, and the speed loop
        settles in about 1 s).
    """

    faults: tuple[float, ...] = (0.2, 0.4, 0.3, 0.1)
    critical_span: float = 1.6
    min_clearance: float = 1.0e-4
    n_bars: tuple[int, int] = (2, 8)
    torque: tuple[float, float] = (0.25, 1.0)
    rise_s: tuple[float, float] = (0.005, 0.08)
    rolling_s: tuple[float, float] = (0.5, 0.65)
    idle_s: tuple[float, float] = (0.45, 0.6)
    lead_s: float = 0.3
    idle_load: tuple[float, float] = (0.0, 0.01)
    idle_fraction: float = 0.4
    fluctuation: tuple[float, float] = (0.0, 0.02)
    snr_db: tuple[float, float] = (28.0, 42.0)
    stiffness: float = 0.10
    damping: float = 0.30
    preload: float = 0.20
    drag: tuple[float, float] = (0.005, 0.05)
    drag_fraction: float = 0.5
    drag_lead_s: float = 1.5
    drag_idle_s: float = 1.0


@dataclass(frozen=True)
class SampleSpec:
    """One library sample's draw (everything :func:`simulate_sample` needs)."""

    gaps: dict[str, float]
    gap_open: dict[str, float]
    clearances: dict[str, float]
    k_scale: dict[str, float]
    c_scale: dict[str, float]
    bearing_params: dict[str, dict[str, float]]
    scenario: Scenario
    snr_db: float
    seed: int
    drag: dict[str, float] = field(default_factory=dict)

    def truth(self, mill: Mill) -> dict[str, Any]:
        """Targets and draws as one flat row."""
        row: dict[str, Any] = {}
        for e in mill.elements:
            row[f"{e.id}.gap"] = self.gaps[e.id]
            row[f"{e.id}.gap_open"] = self.gap_open[e.id]
            row[f"{e.id}.state"] = element_state(e, self.gaps[e.id]).value
            row[f"{e.id}.k_scale"] = self.k_scale[e.id]
            row[f"{e.id}.c_scale"] = self.c_scale[e.id]
        for b in mill.bearings:
            row[f"{b.id}.clearance"] = self.clearances[b.id]
            row[f"{b.id}.state"] = bearing_state(b, self.clearances[b.id]).value
        row["snr_db"] = self.snr_db
        row["seed"] = self.seed
        row["idle_load"] = self.scenario.idle_torque
        row["drag"] = float(sum(self.drag.values()))
        return row


def _class_balanced(rng: np.random.Generator, worn: float, critical: float, span: float,
                    lo: float = 0.0) -> float:
    c = int(rng.integers(3))
    edges = (lo, worn, critical, critical * span)
    return float(rng.uniform(edges[c], edges[c + 1]))


def _element_gaps(mill: Mill, rng: np.random.Generator, ranges: LibraryRanges
                  ) -> dict[str, float]:
    """Gaps with a few faulty elements (``ranges.faults``), the others good."""
    p = np.asarray(ranges.faults, dtype=float)
    if p.ndim != 1 or p.size == 0 or np.any(p < 0) or p.sum() <= 0:
        raise ValueError("The 'faults' range of LibraryRanges must be non-negative "
                         f"probabilities of 0, 1, 2, ... faulty elements. Got {ranges.faults!r}.")
    n = min(int(rng.choice(p.size, p=p / p.sum())), len(mill.elements))
    faulty = set(rng.choice(len(mill.elements), n, replace=False).tolist()) if n else set()
    out = {}
    for i, e in enumerate(mill.elements):
        if i in faulty:
            hi = (e.gap_worn, e.gap_critical) if rng.random() < 0.5 else \
                (e.gap_critical, e.gap_critical * ranges.critical_span)
            out[e.id] = float(rng.uniform(*hi))
        else:
            out[e.id] = float(rng.uniform(0.0, e.gap_worn))
    return out


def draw_sample(mill: Mill, rng: np.random.Generator, *,
                ranges: LibraryRanges = LibraryRanges()) -> SampleSpec:
    """Draw one library sample's wear state, nuisance and scenario."""
    gaps = _element_gaps(mill, rng, ranges)
    opens, ks, cs = {}, {}, {}
    for e in mill.elements:
        opens[e.id] = float(rng.uniform(0.0, gaps[e.id]))
        ks[e.id] = float(1.0 + rng.uniform(-ranges.stiffness, ranges.stiffness))
        cs[e.id] = float(1.0 + rng.uniform(-ranges.damping, ranges.damping))
    cl, bp = {}, {}
    for b in mill.bearings:
        cl[b.id] = _class_balanced(rng, b.clearance_worn, b.clearance_critical,
                                   ranges.critical_span, lo=ranges.min_clearance)
        kk = 1.0 + rng.uniform(-ranges.stiffness, ranges.stiffness, 3)
        cc = 1.0 + rng.uniform(-ranges.damping, ranges.damping, 2)
        pl = 1.0 + rng.uniform(-ranges.preload, ranges.preload)
        bp[b.id] = {"k_bearing": b.k_bearing * kk[0], "k_housing": b.k_housing * kk[1],
                    "c_bearing": b.c_bearing * cc[0], "c_housing": b.c_housing * cc[1]}
        if b.k_housing_open is not None:
            bp[b.id]["k_housing_open"] = b.k_housing_open * kk[2]
        if math.isfinite(b.housing_preload):
            bp[b.id]["housing_preload"] = b.housing_preload * pl
    nom = nominal_torque(mill)
    n_bars = int(rng.integers(ranges.n_bars[0], ranges.n_bars[1] + 1))
    sc = random_scenario(mill, n_bars=n_bars, rng=rng,
                         torque_range=(ranges.torque[0] * nom, ranges.torque[1] * nom),
                         rolling_s=ranges.rolling_s, idle_s=ranges.idle_s, rise_s=ranges.rise_s,
                         lead_s=ranges.lead_s, fluctuation=float(rng.uniform(*ranges.fluctuation)))
    idle = float(rng.uniform(*ranges.idle_load)) if rng.random() < ranges.idle_fraction else 0.0
    sc = dataclasses.replace(sc, idle_torque=idle * nom)
    snr = float(rng.uniform(*ranges.snr_db))
    seed = int(rng.integers(2 ** 31))
    drag: dict[str, float] = {}
    if ranges.drag_fraction > 0:  # from the sample's own seed: the library's stream stays
        r2 = np.random.default_rng((seed, 0xD2A6))
        if r2.random() < ranges.drag_fraction:
            ms = drag_masses(mill)
            # bearing friction follows the bearings' loads and seals, not the inertias: a
            # uniform split over the masses (a J-weighted one put ~3/4 of it on the motor
            # rotor, and the gearbox bearings saw almost none of it)
            w = r2.dirichlet(np.ones(len(ms)))
            total = float(r2.uniform(*ranges.drag)) * nom
            drag = {m: float(total * wi / w.sum()) for m, wi in zip(ms, w)}
            # the simulation starts at rest without it: the speed loop takes the drag up
            # before the first bite; and the pauses are longer, so that the loop has
            # recovered from each release's overspeed and the drag has closed the
            # couplings again before the next bite (plantsim idles 1.5-3 s)
            lead, extra = float(ranges.drag_lead_s), float(ranges.drag_idle_s)
            sc = dataclasses.replace(
                sc, duration=sc.duration + lead + extra * (len(sc.bars) - 1),
                bars=tuple(dataclasses.replace(b, t_bite=b.t_bite + lead + k * extra,
                                               t_release=b.t_release + lead + k * extra)
                           for k, b in enumerate(sc.bars)))
    return SampleSpec(gaps=gaps, gap_open=opens, clearances=cl, k_scale=ks, c_scale=cs,
                      bearing_params=bp, scenario=sc, snr_db=snr, seed=seed, drag=drag)


def recording_from_devices(devices: Iterable[RawDevice], mill: Mill) -> Recording:
    """SI :class:`~ident.io.recording.Recording` of raw device blocks (as a reader makes it).

    Applies each channel's ``scale``/``offset`` and unit (mill-config.md).
    """
    devices = tuple(devices)
    t0 = min(d.t0_ns for d in devices)
    frames, rates = {}, {}
    for d in devices:
        cols = {}
        for i, name in enumerate(d.channels):
            ch = mill.channel(name)
            cols[name] = (ch.scale * d.data[i] + ch.offset) * to_si_factor(ch.quantity.value,
                                                                          ch.unit)
        t = (d.t0_ns - t0) * 1e-9 + np.arange(d.n_samples) / d.rate_hz
        frames[d.name] = pd.DataFrame(cols, index=pd.Index(t, name="time_s"))
        rates[d.name] = d.rate_hz
    return Recording(frames=frames, rates_hz=rates, t0_ns=t0)


class LibrarySimulator:
    """One mill's torsional simulator with the nuisance as parameters, compiled once.

    :func:`ident.model.simulate.simulate` builds and compiles the driveline for
    every call; a library simulates thousands of recordings of one mill, so
    this builds the driveline (with :class:`Nuisance`) and its compiled RK4
    stepper once and then only integrates.  The same equations, step and
    stage-point loads as ``simulate`` (the load is evaluated on a 4 kHz grid
    and interpolated to the stage points by a cubic spline: within 1e-8 of the
    step for the fastest 10 ms ramp).  It pickles without its compiled parts
    (a joblib worker builds its own).

    Parameters
    ----------
    mill : Mill
    rate_hz : float
        Output rate, Hz.
    max_step : float
        Largest RK4 step, s (as ``simulate``).
    compile : bool
        Compile the integrator to C.
    """

    def __init__(self, mill: Mill, *, rate_hz: float = 2000.0, max_step: float = 5e-5,
                 compile: bool = True) -> None:
        self.mill = mill
        self.rate_hz = float(rate_hz)
        self.max_step = float(max_step)
        self.compile = bool(compile)
        self.effect = Nuisance(mill.element_ids)
        self.drag = IdleDrag(drag_masses(mill))
        self._built: tuple[Any, Any] | None = None

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_built"] = None
        return state

    def _build(self) -> tuple[Any, Any]:
        if self._built is None:
            effects = (self.effect, self.drag) if self.drag.mass_ids else (self.effect,)
            drv = build_driveline(self.mill, ModelOptions(bearings=False, effects=effects))
            T = 1.0 / self.rate_hz
            n_sub = max(1, math.ceil(T / self.max_step - 1e-9))
            st = make_stepper(drv, interval=T, n_sub=n_sub, compile=self.compile,
                              stage_inputs=True)
            self._built = (drv, st)
        return self._built

    def params(self, spec: SampleSpec) -> dict[str, float]:
        """Model parameters of a sample (gaps, open parts, nuisance)."""
        p: dict[str, float] = {}
        for e in self.mill.elements:
            p[f"{e.id}.gap"] = spec.gaps[e.id]
            p[f"{e.id}.gap_open"] = spec.gap_open[e.id]
        p.update(self.effect.params(self.mill, spec.gaps, spec.gap_open, spec.k_scale,
                                    spec.c_scale))
        if self.drag.mass_ids:
            p.update(self.drag.params(spec.drag))
        return p

    def simulate(self, spec: SampleSpec) -> SimResult:
        """The noise-free torsional simulation of a sample (at ``rate_hz``)."""
        from scipy.interpolate import CubicSpline

        drv, st = self._build()
        sc = spec.scenario
        N = int(round(sc.duration * self.rate_hz)) + 1
        t = np.arange(N) / self.rate_hz
        grid = np.arange(int(np.ceil(sc.duration * 4000.0)) + 2) / 4000.0
        load = CubicSpline(grid, load_profile(sc, grid))
        U = load(stage_times(st, N)).reshape(N - 1, -1)
        p = drv.params(self.params(spec))
        X, Y_end = integrate(st, drv.x_idle.copy(), U, p, 0.0)
        y0 = np.asarray(drv.out(drv.x_idle, np.array([float(load(0.0))]), p, 0.0)).ravel()
        Y = np.vstack([y0[None, :], Y_end])
        idx = pd.Index(t, name="time_s")
        return SimResult(mill=self.mill, scenario=sc, driveline=drv, params=p,
                         outputs=pd.DataFrame(Y, index=idx, columns=list(drv.output_names)),
                         states=pd.DataFrame(X, index=idx, columns=list(drv.state_names)),
                         rate_hz=self.rate_hz, meta={"n_sub": st.n_sub, "compiled": st.compiled})


def simulate_sample(mill: Mill, spec: SampleSpec, *, bearings: bool = True,
                    torque_rate_hz: float = 2000.0, accel_rate_hz: float = 10_000.0,
                    simulator: LibrarySimulator | None = None) -> tuple[Recording, SimResult]:
    """Simulate one library sample: torsion, bearings' radial models, sensors.

    Parameters
    ----------
    mill : Mill
    spec : SampleSpec
    bearings : bool
        Also the bearings' radial models and the accelerometer channels.
    torque_rate_hz, accel_rate_hz : float
        Rates of the torque and acceleration channels, Hz.
    simulator : LibrarySimulator, optional
        Reuse one for many samples of the mill (it keeps its compiled integrator).

    Returns
    -------
    recording : Recording
        What a reader would make of the sensors' output (SI).
    result : SimResult
        The noise-free torsional simulation (at ``torque_rate_hz``).
    """
    if simulator is None or simulator.mill is not mill or \
            simulator.rate_hz != float(torque_rate_hz):
        simulator = LibrarySimulator(mill, rate_hz=torque_rate_hz)
    res = simulator.simulate(spec)
    rng = np.random.default_rng(spec.seed)
    torque_names = [c.name for c in mill.channels if c.quantity.value != "acceleration"]
    devices = list(sensor_devices(res, rng=rng, snr_db=spec.snr_db, torque_rate_hz=torque_rate_hz,
                                  channels=torque_names))
    accel = [c for c in mill.acceleration_channels()]
    if bearings and mill.bearings and accel:
        # radial models at the accelerometers' rate, driven by the interpolated mesh torques
        n_hi = int(round(res.time[-1] * accel_rate_hz)) + 1
        t_hi = np.arange(n_hi) / accel_rate_hz
        hi: dict[str, np.ndarray] = {}
        for b in mill.bearings:
            p = dict(spec.bearing_params.get(b.id, {}))
            p["clearance"] = spec.clearances[b.id]
            u = np.interp(t_hi, res.time, res.outputs[f"tau:{b.mesh}"].to_numpy())
            r = simulate_radial(b, u, accel_rate_hz, params=p)
            for col in ("acc:h", "acc:v"):
                kind, rest = col.split(":")
                hi[f"{kind}:{b.id}:{rest}"] = r[col].to_numpy()
        out = pd.DataFrame(hi, index=pd.Index(t_hi, name="time_s"))
        hires = dataclasses.replace(res, outputs=out, states=out.iloc[:, :0],
                                    rate_hz=accel_rate_hz)
        devices += sensor_devices(hires, rng=rng, snr_db=spec.snr_db,
                                  torque_rate_hz=accel_rate_hz, accel_rate_hz=accel_rate_hz,
                                  channels=[c.name for c in accel])
    return recording_from_devices(devices, mill), res


def sample_features(mill: Mill, spec: SampleSpec, *, reference: LinearReference,
                    bearings: bool = True, options: FeatureOptions = FeatureOptions(),
                    simulator: LibrarySimulator | None = None) -> pd.Series:
    """Simulate a sample and return its recording's feature vector."""
    rec, _ = simulate_sample(mill, spec, bearings=bearings, simulator=simulator)
    steps = []
    for bar in spec.scenario.bars:
        steps += [bar.t_step_bite, bar.t_step_release]
    tf = transient_features(rec, mill, steps, reference=reference, options=options)
    return recording_features(tf)


@dataclass(frozen=True)
class Library:
    """Simulated recordings' features and their truth.

    Attributes
    ----------
    features : DataFrame
        One row per sample (:func:`ident.features.recording_features`).
    truth : DataFrame
        Same rows: ``{ID}.gap``, ``{ID}.gap_open``, ``{ID}.state`` per element,
        ``{ID}.clearance``, ``{ID}.state`` per bearing, and the nuisance draws.
    mill_hash : str
        :meth:`~ident.description.Mill.content_hash` of the mill the library was
        simulated from.
    ranges : LibraryRanges
    options : FeatureOptions
    random_state : int or None
    bearings : bool
        Whether the bearings' radial models and accelerometers were simulated.
    """

    features: pd.DataFrame
    truth: pd.DataFrame
    mill_hash: str
    ranges: LibraryRanges = field(default_factory=LibraryRanges)
    options: FeatureOptions = field(default_factory=FeatureOptions)
    random_state: int | None = None
    bearings: bool = True

    def __len__(self) -> int:
        return len(self.features)

    def concat(self, other: "Library") -> "Library":
        """Both libraries' samples (same mill)."""
        return dataclasses.replace(
            self, features=pd.concat([self.features, other.features], ignore_index=True),
            truth=pd.concat([self.truth, other.truth], ignore_index=True))


def _chunk_worker(mill: Mill, specs: list[SampleSpec], bearings: bool, options: FeatureOptions,
                  reference: LinearReference) -> list[tuple[pd.Series, dict[str, Any]]]:
    """Simulate a chunk of samples with one simulator (its integrator compiled once)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sim = LibrarySimulator(mill)
    return [(sample_features(mill, s, reference=reference, bearings=bearings, options=options,
                             simulator=sim), s.truth(mill)) for s in specs]


def _chunks(seq: list, n: int) -> Iterator[list]:
    for i in range(0, len(seq), n):
        yield seq[i:i + n]


def simulate_library(mill: Mill, *, n: int, random_state: int | None = 0, n_jobs: int = 1,
                     bearings: bool = True, ranges: LibraryRanges = LibraryRanges(),
                     options: FeatureOptions = FeatureOptions(), progress: bool = False,
                     chunk: int | None = None) -> Library:
    """Simulate ``n`` recordings of random wear states and extract their features.

    Parameters
    ----------
    mill : Mill
    n : int
        Number of recordings.
    random_state : int or None
        Seed of every draw (the library is reproducible for a given seed).
    n_jobs : int
        Worker processes (joblib); 1 runs in this process.
    bearings : bool
        Simulate the bearings' radial models and accelerometer channels.
    ranges : LibraryRanges
    options : FeatureOptions
    progress : bool
        Show a progress bar (tqdm) on stderr.
    chunk : int, optional
        Samples per job (default: about four jobs per worker, at least 8 samples).

    Returns
    -------
    Library
    """
    if n < 1:
        raise ValueError(f"The 'n' parameter of simulate_library must be >= 1. Got {n} instead.")
    rng = np.random.default_rng(random_state)
    specs = [draw_sample(mill, rng, ranges=ranges) for _ in range(n)]
    if chunk is None:
        chunk = max(8, int(np.ceil(n / (4 * max(n_jobs, 1)))))
    chunks = list(_chunks(specs, max(1, int(chunk))))
    # the baseline's unit responses once, here; the workers get them with the reference
    reference = LinearReference(mill)
    seen = sorted({c.element for c in mill.torque_channels()}, key=mill.element_ids.index)
    if seen:
        reference.warm(2000.0, nearest_load_elements(mill, seen))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=f"simulating {mill.name} library", unit="rec", leave=False)
    results: list[tuple[pd.Series, dict[str, Any]]] = []
    if n_jobs == 1:
        for c in chunks:
            results.extend(_chunk_worker(mill, c, bearings, options, reference))
            if bar is not None:
                bar.update(len(c))
    else:
        from joblib import Parallel, delayed

        par = Parallel(n_jobs=n_jobs, return_as="generator")
        for out in par(delayed(_chunk_worker)(mill, c, bearings, options, reference)
                       for c in chunks):
            results.extend(out)
            if bar is not None:
                bar.update(len(out))
    if bar is not None:
        bar.close()
    feats = pd.DataFrame([r[0] for r in results]).reset_index(drop=True)
    truth = pd.DataFrame([r[1] for r in results]).reset_index(drop=True)
    return Library(features=feats, truth=truth, mill_hash=mill.content_hash(), ranges=ranges,
                   options=options, random_state=random_state, bearings=bearings)
