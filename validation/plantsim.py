"""An independent plant simulator: torsional telemetry as a real plant records it.

Written from ``../shared/spec/mill-config.md`` and ``telemetry.md`` alone; it reads
the frozen :class:`ident.Mill` description for parameters and never calls
``ident.model`` or ``ident.fit`` (nor ident's unit table or writers), so that
agreement with ident is evidence, not tautology.

What it models
--------------
*Physics* (SI, reduced to the motor shaft).  States: angle deviation ``phi`` and speed
deviation ``v`` from the nominal rotation ``w0 * t`` of every mass, plus the speed
loop's integral ``z``.  Element ``e`` (``from -> to``) transmits
``tau = g(delta) + c * d(delta)/dt`` with ``delta = phi_from - phi_to``; ``g`` is the
dead zone of seed Fig. 1a (slope ``k`` beyond the flanks, ``k_gap`` inside, continuous)
with the optional softening/hardening knee of mill-config.md.  The gap geometry is
fixed per element: drive-side flank at ``hi = gap * gap_open_design / gap_design``,
back flank at ``lo = hi - gap``; the *open part* at a moment is ``hi - delta``.  The
motor has a PI speed loop at the mill's nominal speed with an ideal torque loop,
``Tm = clip(-kp * v_m + ki * z, +-torque_limit)``, ``z' = -v_m``.  The rolling load
``L(t)`` acts against rotation on the ``[load]`` masses by their shares; a constant
idle friction acts on the masses upstream of the floating elements (below).

*Integration.*  The right-hand side is piecewise linear: in a fixed *mode* (which
flank interval each element is in, whether the motor torque is limited) the system is
LTI, ``x' = M x + b L(t) + e``.  Each step of ``h = 1 / sim_rate`` (20 kHz) advances
``x`` exactly for the mode found at the start of the step, with ``L`` linear over the
step (first-order hold): ``x+ = Phi x + G [L_k, L_k+1 - L_k, 1]``, ``Phi, G`` from one
matrix exponential per mode (cached; a recording meets a few dozen modes).  Because
``g`` is continuous, a contact that starts inside a step costs a local error of order
``k * v * h^2``; the step-halving test checks convergence.

*Bites and releases.*  Each bar: bite ramp (5-60 ms), rolling (1.5-4 s), release ramp
(5-80 ms), idle (1.5-3 s); ramp shapes raised cosine, linear, exponential approach or
an asymmetric S (regularised incomplete beta).  The rolling level is drawn per bar
(0.6-1.1 x the mill's nominal level), with a linear trend (+-3 % over the bar) and a
slow fluctuation (1-3 sinusoids, 0.3-2 Hz, 0.3-2 % in all).

*Gap position at each bite.*  *Floating* elements (a gap and a designed
``gap_open > 0``, or a gap and nothing but load masses beyond them: the spindles) carry
no torque between bars, because the idle friction acts only on the masses upstream of
them; so the rolls float in the spindle clearance.  Their open part at each bite is
drawn uniformly in ``[0, gap]`` and realised by *repositioning*: the recording starts
from the steady state with bar 1's open parts; for every later bar, at a moment 60 %
into the preceding idle (>= 0.9 s after the release, when the release rattle has
died out), the masses beyond each floating element are turned rigidly so that the
element's open part is the drawn one, and given the speed of the element's driving
side (the element carries zero torque before and after, so no torque channel sees
the move).  Other gapped elements are held against their drive flank by the idle
friction (open part 0, the mill file's ``gap_open`` for them).  The truth records the
open parts realised at the start of every load ramp.

*Recording chain* per channel: physics at the simulation rate -> white sensor noise
at that rate -> anti-alias filter (FIR ``firwin`` with cutoff 0.40-0.45 of the
recorded rate, group delay compensated or not; or a DC-normalised Butterworth or
Chebyshev-I IIR) and decimation to the recorded rate (1000, 2000, 2500, 4000 or
5000 Hz) -> a small extra white noise -> constant offset (0-2 % of the channel's
rolling level), drift (linear + a 0.02-0.2 Hz sinusoid, 0-1 %) and a random walk
(0-0.5 % at the end) -> 16-bit quantisation over a round full scale (the smallest of
1, 2, 5 x 10^k holding twice the largest value; step = full scale / 65536).  The total
noise std after the chain is 0.2-2 % of the channel's rolling level (log-uniform).

*Accelerometers* (when the mill maps acceleration channels on its ``[[bearing]]`` s): the
radial model of mill-config.md per bearing (shaft and housing point masses in the plane,
the whole mesh force along the line of action, gravity on the shaft, contact beyond the
radial clearance, housing on a bilinear spring that softens above ``housing_preload``),
driven by the simulated mesh torque, no feedback; fixed-step RK4 at 5 x the torsional
rate (100 kHz) in a small C kernel built with ``cc`` on first use (without a compiler
the accelerometers are left out, with a warning and a note in the truth).  Housing
acceleration -> AC coupling (first-order high-pass 0.5-3 Hz) -> white noise -> an
anti-alias filter drawn as above, decimation to 10, 12.5, 20 or 25 kHz -> extra noise,
a tiny offset -> 16-bit quantisation; a second device starting 0-50 ms after the torque
device.  The rattle after a release (impacts in the clearance) is chaotic: step halving
changes its samples, not its level.

Not modelled: speed channels, dropouts and other telemetry faults, drivelines with loops.

Use
---
>>> import ident, numpy as np                                        # doctest: +SKIP
>>> from validation.plantsim import draw_plant, simulate_plant, write_plant
>>> mill = ident.load_mill("data/mills/cold-s5.toml")
>>> draw = draw_plant(mill, np.random.default_rng(7), n_bars=2)
>>> rec = simulate_plant(mill, draw)
>>> write_plant(rec, "/tmp/rec.mcap")        # also /tmp/rec.truth.json
>>> # or in one call: make_recording(mill, 7, "/tmp/rec.csv")
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import linalg, signal, special

from ident.description import Mill, Quantity, StiffnessKind

__all__ = ["SIM_RATE_HZ", "RECORD_RATES_HZ", "ACCEL_RATES_HZ", "Ramp", "Bar", "AntiAlias",
           "ChannelNuisance", "AccelChannel", "AccelDraw", "PlantDraw", "PlantDevice",
           "PlantRecording", "BearingKernelError", "nominal_level", "floating_elements",
           "load_fractions", "draw_plant", "load_profile", "simulate_plant", "write_plant",
           "make_recording", "truth_path", "accel_csv_path"]

#: Default physics rate, Hz (an integer multiple of every recorded rate).
SIM_RATE_HZ = 20_000.0
#: Recorded rates drawn from, Hz.
RECORD_RATES_HZ = (1000.0, 2000.0, 2500.0, 4000.0, 5000.0)
#: Accelerometer rates drawn from, Hz.
ACCEL_RATES_HZ = (10000.0, 12500.0, 20000.0, 25000.0)
#: The radial bearing model runs at this multiple of the torsional rate (100 kHz).
BEARING_OVERSAMPLE = 5
#: Standard gravity, m/s^2.
G0 = 9.80665
#: Channel units this generator writes, and their factor to SI (own table, not ident's).
UNIT_TO_SI = {"N*m": 1.0, "kN*m": 1.0e3, "MN*m": 1.0e6}
ACCEL_UNIT_TO_SI = {"m/s^2": 1.0, "g": G0}
#: 2025-01-01T00:00:00Z, ns: recordings start within a year after it.
_EPOCH_NS = 1_735_689_600_000_000_000
_RAMP_KINDS = ("cosine", "linear", "exp", "beta")
_DEVICE = "/telemetry/torque"
_ACCEL_DEVICE = "/telemetry/accel"


# ==== topology ===========================================================================
@dataclass(frozen=True)
class _Tree:
    """The driveline as a tree rooted at the motor mass."""

    ids: tuple[str, ...]
    J: np.ndarray                  # (n,)
    fr: np.ndarray                 # (E,) index of each element's from mass
    to: np.ndarray                 # (E,) index of each element's to mass
    motor: int
    share: np.ndarray              # (n,) load share per mass
    away: tuple[tuple[int, ...], ...]  # per element: the masses on its side away from the motor
    away_is_to: tuple[bool, ...]   # per element: whether its `to` mass is on the away side
    order: tuple[tuple[int, int, int], ...]  # (element, known mass, unknown mass) from the motor


def _tree(mill: Mill) -> _Tree:
    """Index the mill as a tree rooted at the motor; raise ValueError for loops."""
    ids = mill.mass_ids
    idx = {m: i for i, m in enumerate(ids)}
    n, E = len(ids), len(mill.elements)
    fr = np.array([idx[e.from_] for e in mill.elements])
    to = np.array([idx[e.to] for e in mill.elements])
    if E != n - 1:
        raise ValueError(f"plantsim needs a tree driveline (n_elements = n_masses - 1); "
                         f"{mill.name} has {n} masses and {E} elements")
    adj: dict[int, list[tuple[int, int]]] = {i: [] for i in range(n)}
    for j in range(E):
        adj[fr[j]].append((to[j], j))
        adj[to[j]].append((fr[j], j))
    motor = idx[mill.motor.mass]
    parent_el = {motor: -1}
    order: list[tuple[int, int, int]] = []
    q = deque([motor])
    while q:
        m = q.popleft()
        for nb, j in adj[m]:
            if nb not in parent_el:
                parent_el[nb] = j
                order.append((j, m, nb))
                q.append(nb)
    if len(parent_el) != n:
        raise ValueError(f"{mill.name}: the driveline is not connected")
    children: dict[int, list[int]] = {i: [] for i in range(n)}
    for j, known, unknown in order:
        children[known].append(unknown)

    def subtree(m: int) -> tuple[int, ...]:
        out, stack = [], [m]
        while stack:
            u = stack.pop()
            out.append(u)
            stack.extend(children[u])
        return tuple(sorted(out))

    away = [()] * E
    away_is_to = [True] * E
    for j, known, unknown in order:
        away[j] = subtree(unknown)
        away_is_to[j] = unknown == to[j]
    share = np.zeros(n)
    for m, s in zip(mill.load.masses, mill.load.share):
        share[idx[m]] += s
    return _Tree(ids=ids, J=np.array([m.J for m in mill.masses]), fr=fr, to=to, motor=motor,
                 share=share, away=tuple(away), away_is_to=tuple(away_is_to),
                 order=tuple(order))


def _static_torques(tree: _Tree, ext_on_mass: np.ndarray) -> np.ndarray:
    """Element torques (from -> to) at constant speed, given the external torque on each mass.

    ``ext_on_mass`` is the torque *opposing* rotation on each mass (load + friction), N*m.
    """
    out = np.empty(len(tree.away))
    for j, side in enumerate(tree.away):
        s = float(ext_on_mass[list(side)].sum())
        out[j] = s if tree.away_is_to[j] else -s
    return out


def load_fractions(mill: Mill) -> dict[str, float]:
    """Static share of the total rolling torque each element carries (tree), own code."""
    tree = _tree(mill)
    fr = _static_torques(tree, tree.share)
    return {e.id: float(f) for e, f in zip(mill.elements, fr)}


def _distance_to_load(mill: Mill) -> dict[str, int]:
    """Elements between each element and the nearest load mass (0 = touching one)."""
    ids = mill.mass_ids
    dist = {m: -1 for m in ids}
    q = deque()
    for m in mill.load.masses:
        dist[m] = 0
        q.append(m)
    while q:
        m = q.popleft()
        for e in mill.elements:
            for a, b in ((e.from_, e.to), (e.to, e.from_)):
                if a == m and dist[b] < 0:
                    dist[b] = dist[m] + 1
                    q.append(b)
    return {e.id: min(dist[e.from_], dist[e.to]) for e in mill.elements}


def floating_elements(mill: Mill) -> tuple[str, ...]:
    """Elements that float in their gap between bars (spindle-like), by the default rule.

    An element floats when it has a designed gap and either a designed ``gap_open > 0``
    or only load masses on its side away from the motor.
    """
    tree = _tree(mill)
    loads = {tree.ids.index(m) for m in mill.load.masses}
    out = []
    for j, e in enumerate(mill.elements):
        if e.gap > 0 and (e.gap_open > 0 or set(tree.away[j]) <= loads):
            out.append(e.id)
    return tuple(out)


def nominal_level(mill: Mill) -> float:
    """Nominal rolling torque of a mill, N*m reduced: 0.4 x the motor's torque limit.

    Without a torque limit: 0.01 rad of deflection of the softest element.
    hsm-f1 gives 400 kN*m, cold-s5 44 kN*m.
    """
    if mill.motor.torque_limit is not None:
        return 0.4 * mill.motor.torque_limit
    return 0.01 * min(e.k for e in mill.elements)


# ==== stiffness characteristics ===========================================================
@dataclass(frozen=True)
class _Char:
    """A continuous piecewise-linear characteristic ``g(delta)``.

    Interval ``i`` is ``bp[i-1] < delta <= bp[i]``; ``g = slope[i] * delta + icpt[i]``.
    """

    bp: tuple[float, ...]
    slope: tuple[float, ...]
    icpt: tuple[float, ...]
    hi: float          # drive-side flank
    lo: float          # back flank


def _characteristic(e, gap: float) -> _Char:
    """The element's g1 dead zone (plus knee) for a total gap ``gap`` (rad, reduced)."""
    frac = e.gap_open / e.gap if e.gap > 0 else 0.0
    hi = frac * gap
    lo = hi - gap
    knee = e.knee if (e.stiffness is not StiffnessKind.LINEAR and e.knee and e.k_after) else None
    if gap > 0:
        bp, slope, zero = [lo, hi], [e.k, e.k_gap, e.k], 1
    else:
        bp, slope, zero = [], [e.k], 0
    if knee is not None:
        bp = [lo - knee] + bp + [hi + knee]
        slope = [e.k_after] + slope + [e.k_after]
        zero += 1
    icpt = [0.0] * len(slope)
    for i in range(zero, len(slope) - 1):        # continuity outward from delta = 0
        icpt[i + 1] = icpt[i] + (slope[i] - slope[i + 1]) * bp[i]
    for i in range(zero, 0, -1):
        icpt[i - 1] = icpt[i] + (slope[i] - slope[i - 1]) * bp[i - 1]
    return _Char(tuple(bp), tuple(slope), tuple(icpt), hi, lo)


def _g(ch: _Char, d: np.ndarray) -> np.ndarray:
    """Evaluate ``g`` (vectorised); the interval rule matches the integrator's modes."""
    i = np.searchsorted(np.asarray(ch.bp, dtype=float), d, side="left")
    return np.asarray(ch.slope)[i] * d + np.asarray(ch.icpt)[i]


def _g_inverse(ch: _Char, torque: float) -> float:
    """Deflection carrying ``torque``; at zero torque inside a dead zone, the drive flank."""
    if torque == 0.0:
        return ch.hi if _g(ch, np.array([ch.hi]))[0] == 0.0 else 0.0
    up = torque > 0
    flank = ch.hi if up else ch.lo
    start = flank if _g(ch, np.array([flank]))[0] == 0.0 else 0.0   # dead zone or k_gap
    beyond = [p for p in ch.bp if (p > start if up else p < start)]
    beyond = sorted(beyond, reverse=not up)
    far = (beyond[-1] if beyond else start) + (1.0 if up else -1.0)
    ds = np.array([start] + beyond + [far])
    gs = np.abs(_g(ch, ds))
    T = abs(torque)
    if T >= gs[-1]:
        return float(ds[-1] + (T - gs[-1]) / (gs[-1] - gs[-2]) * (ds[-1] - ds[-2]))
    return float(np.interp(T, gs, ds))


# ==== what is drawn ======================================================================
@dataclass(frozen=True)
class Ramp:
    """One load ramp: ``shape`` from 0 to 1 over ``duration`` s starting at ``t_start``.

    ``kind``: ``cosine`` (raised cosine), ``linear``, ``exp`` (exponential approach,
    ``p1`` = rate, 2-5) or ``beta`` (asymmetric S: regularised incomplete beta with
    ``p1, p2`` in 1.3-3).
    """

    t_start: float
    duration: float
    kind: str
    p1: float = 0.0
    p2: float = 0.0

    def shape(self, u: np.ndarray) -> np.ndarray:
        """Fraction of the ramp done at normalised time ``u`` (clipped to [0, 1])."""
        u = np.clip(u, 0.0, 1.0)
        if self.kind == "cosine":
            return 0.5 - 0.5 * np.cos(np.pi * u)
        if self.kind == "linear":
            return u
        if self.kind == "exp":
            return -np.expm1(-self.p1 * u) / -math.expm1(-self.p1)
        if self.kind == "beta":
            return special.betainc(self.p1, self.p2, u)
        raise ValueError(f"unknown ramp kind {self.kind!r}")

    def half_time(self) -> float:
        """Time the ramp is half done, s (absolute, simulation time)."""
        uu = np.linspace(0.0, 1.0, 20001)
        return self.t_start + self.duration * float(np.interp(0.5, self.shape(uu), uu))


@dataclass(frozen=True)
class Bar:
    """One rolled bar.

    Attributes
    ----------
    bite, release : Ramp
        Load ramps (times in simulation seconds; the recording starts ``PlantDraw.t_rec0``
        later).
    level : float
        Rolling level, N*m reduced (total over the load masses).
    trend : float
        Relative change of the level from the bite's start to the release's start.
    fluct : tuple of (amplitude, frequency Hz, phase rad)
        Slow fluctuation, amplitudes relative to ``level``.
    gap_open : mapping of element id to rad
        Open part drawn for the floating elements at this bar's bite.
    t_reposition : float or None
        When the floating elements are repositioned before this bar (None for bar 1:
        the initial state has them).
    idle_after : float
        Idle after the release ramp, s.
    """

    bite: Ramp
    release: Ramp
    level: float
    trend: float
    fluct: tuple[tuple[float, float, float], ...]
    gap_open: Mapping[str, float]
    t_reposition: float | None
    idle_after: float


@dataclass(frozen=True)
class AntiAlias:
    """The anti-alias filter of the recorder (at the simulation rate).

    ``kind``: ``fir`` (``numtaps``, ``window``, ``kaiser_beta``, ``compensated``: the
    group delay taken out of the timestamps), ``butter`` or ``cheby1`` (``order``,
    ``ripple_db``; DC gain normalised to 1, never compensated).  ``cutoff`` is a
    fraction of the recorded rate.
    """

    kind: str
    cutoff: float
    numtaps: int = 0
    window: str = ""
    kaiser_beta: float = 0.0
    compensated: bool = False
    order: int = 0
    ripple_db: float = 0.0


@dataclass(frozen=True)
class ChannelNuisance:
    """Everything drawn for one channel's recording chain, in the channel's unit.

    Attributes
    ----------
    level : float
        The channel's rolling level (mean bar level x load fraction x ratio), in unit.
    noise_frac : float
        Total noise std after the chain / level.
    post_share : float
        Share of the noise variance added after decimation.
    offset : float
    drift_linear : float
        Drift reached at the end of the recording (linear part).
    drift_sine, drift_freq, drift_phase : float
        Sinusoidal drift amplitude, Hz, rad.
    walk_end_std : float
        Std of the random walk at the end of the recording.
    """

    name: str
    level: float
    noise_frac: float
    post_share: float
    offset: float
    drift_linear: float
    drift_sine: float
    drift_freq: float
    drift_phase: float
    walk_end_std: float


@dataclass(frozen=True)
class AccelChannel:
    """Nuisance of one accelerometer channel, relative to its level.

    The level is the 99.9th percentile of the channel's noise-free recorded ``|a|`` (the
    rattle bursts); ``noise_frac`` and ``offset_frac`` are fractions of it.
    """

    name: str
    noise_frac: float
    post_share: float
    offset_frac: float


@dataclass(frozen=True)
class AccelDraw:
    """The accelerometer conditioner: its own rate, start, filters and channels.

    ``t_offset`` is its first sample after the torque device's, s; ``highpass_hz`` the
    sensors' AC coupling (first order).
    """

    rate_hz: float
    t_offset: float
    antialias: AntiAlias
    highpass_hz: float
    channels: tuple[AccelChannel, ...]
    block_s: float = 0.1


@dataclass(frozen=True)
class PlantDraw:
    """Every drawn parameter of one recording (see :func:`draw_plant` for the ranges).

    Times are simulation seconds; the first recorded sample is at ``t_rec0``
    (``decim_phase`` simulation samples into the run).
    """

    mill: str
    gaps: Mapping[str, float]
    floating: tuple[str, ...]
    friction: Mapping[str, float]
    bars: tuple[Bar, ...]
    sim_rate_hz: float
    rate_hz: float
    decim_phase: int
    duration: float
    antialias: AntiAlias
    channels: tuple[ChannelNuisance, ...]
    t0_ns: int
    noise_seed: int
    block_s: float = 0.1
    clearances: Mapping[str, float] = field(default_factory=dict)
    accel: AccelDraw | None = None

    @property
    def bearing_rate_hz(self) -> float:
        """Rate of the radial bearing model, Hz."""
        return BEARING_OVERSAMPLE * self.sim_rate_hz

    @property
    def t_rec0(self) -> float:
        """Simulation time of the first recorded sample, s."""
        return self.decim_phase / self.sim_rate_hz


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _draw_ramp(rng: np.random.Generator, t_start: float, lo_s: float, hi_s: float) -> Ramp:
    kind = _RAMP_KINDS[int(rng.integers(len(_RAMP_KINDS)))]
    dur = _log_uniform(rng, lo_s, hi_s)
    p1 = p2 = 0.0
    if kind == "exp":
        p1 = float(rng.uniform(2.0, 5.0))
    elif kind == "beta":
        p1, p2 = (float(v) for v in rng.uniform(1.3, 3.0, size=2))
    return Ramp(float(t_start), dur, kind, p1, p2)


def _draw_fluct(rng: np.random.Generator) -> tuple[tuple[float, float, float], ...]:
    n = int(rng.integers(1, 4))
    total = float(rng.uniform(0.003, 0.02))
    w = rng.dirichlet(np.ones(n))
    return tuple((float(total * wi), float(rng.uniform(0.3, 2.0)),
                  float(rng.uniform(0.0, 2 * math.pi))) for wi in w)


def _draw_bars(rng: np.random.Generator, n_bars: int, level0: float, t_first: float,
               gaps: Mapping[str, float], floating: Sequence[str]) -> tuple[Bar, ...]:
    bars: list[Bar] = []
    t = t_first
    t_rep = None
    for _ in range(n_bars):
        bite = _draw_ramp(rng, t, 0.005, 0.060)
        roll = float(rng.uniform(1.5, 4.0))
        release = _draw_ramp(rng, bite.t_start + bite.duration + roll, 0.005, 0.080)
        idle = float(rng.uniform(1.5, 3.0))
        opens = {eid: float(rng.uniform(0.0, gaps[eid])) for eid in floating}
        bars.append(Bar(bite=bite, release=release, level=float(rng.uniform(0.6, 1.1) * level0),
                        trend=float(rng.uniform(-0.03, 0.03)), fluct=_draw_fluct(rng),
                        gap_open=opens, t_reposition=t_rep, idle_after=idle))
        t_end = release.t_start + release.duration
        t_rep = round(t_end + 0.6 * idle, 3)
        t = t_end + idle
    return tuple(bars)


def _draw_antialias(rng: np.random.Generator, decim: int) -> AntiAlias:
    kind = ("fir", "butter", "cheby1")[int(rng.integers(3))]
    cutoff = float(rng.uniform(0.40, 0.45))
    if kind == "fir":
        window = ("hamming", "blackman", "kaiser")[int(rng.integers(3))]
        numtaps = 2 * int(round(decim * rng.uniform(3.0, 8.0))) + 1
        return AntiAlias(kind, cutoff, numtaps=numtaps, window=window,
                         kaiser_beta=float(rng.uniform(5.0, 9.0)) if window == "kaiser" else 0.0,
                         compensated=bool(rng.integers(2)))
    order = int(rng.integers(4, 9))
    ripple = float(rng.uniform(0.1, 1.0)) if kind == "cheby1" else 0.0
    return AntiAlias(kind, cutoff, order=order, ripple_db=ripple)


def _draw_channel(rng: np.random.Generator, name: str, level: float) -> ChannelNuisance:
    drift = float(rng.uniform(0.0, 0.01)) * level
    split = float(rng.uniform(0.0, 1.0))
    return ChannelNuisance(
        name=name, level=level, noise_frac=_log_uniform(rng, 0.002, 0.02),
        post_share=float(rng.uniform(0.0, 0.3)),
        offset=float(rng.uniform(-0.02, 0.02)) * level,
        drift_linear=float(rng.choice([-1.0, 1.0])) * split * drift,
        drift_sine=(1.0 - split) * drift, drift_freq=_log_uniform(rng, 0.02, 0.2),
        drift_phase=float(rng.uniform(0.0, 2 * math.pi)),
        walk_end_std=float(rng.uniform(0.0, 0.005)) * level)


def _draw_friction(mill: Mill, rng: np.random.Generator, floating: Sequence[str],
                   level0: float) -> dict[str, float]:
    """Idle friction (0.5-5 % of the nominal level) on the masses upstream of floating elements."""
    tree = _tree(mill)
    beyond = set()
    for j, e in enumerate(mill.elements):
        if e.id in floating:
            beyond.update(tree.away[j])
    eligible = [i for i in range(len(tree.ids)) if i not in beyond and i != tree.motor]
    total = float(rng.uniform(0.005, 0.05)) * level0
    if not eligible:
        return {tree.ids[tree.motor]: total}
    w = tree.J[eligible] * rng.uniform(0.5, 1.5, size=len(eligible))
    w = w / w.sum()
    return {tree.ids[i]: float(total * wi) for i, wi in zip(eligible, w)}


def _unit_factor(unit: str) -> float:
    try:
        return UNIT_TO_SI[unit]
    except KeyError:
        raise ValueError(f"plantsim writes torque in {sorted(UNIT_TO_SI)}; got {unit!r}") from None


def draw_plant(mill: Mill, rng: np.random.Generator, *, gaps: Mapping[str, float] | None = None,
               n_bars: int = 2, rate_hz: float | None = None,
               sim_rate_hz: float = SIM_RATE_HZ, level: float | None = None,
               floating: Sequence[str] | None = None,
               first_bite_s: float | None = None,
               clearances: Mapping[str, float] | None = None, accelerometers: bool = True,
               accel_rate_hz: float | None = None) -> PlantDraw:
    """Draw every parameter of one recording from broad ranges.

    Parameters
    ----------
    mill : Mill
        The stand (a tree driveline with torque channels in N*m, kN*m or MN*m).
    rng : numpy.random.Generator
        The only source of randomness (the draw is deterministic given it).
    gaps : mapping of element id to rad, optional
        Total gaps (reduced) to use; elements not named keep their designed gap.
        Without it, every element with a designed gap > 0 gets 0.5-3 x that gap
        (log-uniform) and the others stay tight.
    n_bars : int
        Bars rolled.
    rate_hz : float, optional
        Recorded rate; drawn from 1000, 2000, 2500, 4000, 5000 Hz otherwise.
    sim_rate_hz : float
        Physics rate (an integer multiple of the recorded rate).
    level : float, optional
        Nominal rolling torque, N*m reduced (default :func:`nominal_level`).
    floating : sequence of str, optional
        Elements that float in their gap between bars (default
        :func:`floating_elements`).
    first_bite_s : float, optional
        Start of the first bite ramp, s (default drawn in 1.0-2.5 s).
    clearances : mapping of bearing id to m, optional
        Radial bearing clearances; bearings not named get 0.5-10 x the designed one
        (log-uniform).
    accelerometers : bool
        Draw the accelerometer conditioner (when the mill maps acceleration channels on
        its bearings); drawn after everything else, so the torsional draw of a seed does
        not depend on it.
    accel_rate_hz : float, optional
        Accelerometer rate; drawn from 10000, 12500, 20000, 25000 Hz otherwise (a
        divisor of 5 x ``sim_rate_hz``).

    Returns
    -------
    PlantDraw

    Notes
    -----
    Ranges: per bar the level 0.6-1.1 x nominal, trend +-3 %, fluctuation 1-3 sinusoids
    0.3-2 Hz totalling 0.3-2 %, bite ramp 5-60 ms and release ramp 5-80 ms (log-uniform;
    shape raised cosine, linear, exponential approach with rate 2-5, or incomplete-beta
    S with exponents 1.3-3), rolling 1.5-4 s, idle 1.5-3 s; floating elements' open part
    at each bite uniform in [0, gap]; idle friction 0.5-5 % of nominal, spread over the
    masses upstream of the floating elements in proportion to J x U(0.5, 1.5).
    Recorder: anti-alias FIR (3-8 x decimation factor taps either side, Hamming,
    Blackman or Kaiser beta 5-9, delay compensated or not) or Butterworth / Chebyshev-I
    (order 4-8, ripple 0.1-1 dB), cutoff 0.40-0.45 x recorded rate, decimation phase
    uniform; per channel the total noise std 0.2-2 % of its rolling level (log-uniform),
    0-30 % of its variance added after decimation, offset +-2 %, drift 0-1 % split
    between a linear part and a 0.02-0.2 Hz sinusoid, random walk 0-0.5 % at the end.
    Recording start within 2025 (``t0_ns``); MCAP block length 0.05-0.5 s.
    Accelerometers: clearance 0.5-10 x designed (log-uniform), device start 0-50 ms after
    the torque device's, AC coupling 0.5-3 Hz (log-uniform), an anti-alias filter drawn as
    above, per channel noise 0.1-1 % of its level (log-uniform, 0-30 % after decimation)
    and offset +-0.2 %.
    """
    if n_bars < 1:
        raise ValueError(f"n_bars must be >= 1; got {n_bars}")
    tree = _tree(mill)
    level0 = float(level) if level is not None else nominal_level(mill)
    if gaps is None:
        drawn = {e.id: (_log_uniform(rng, 0.5, 3.0) * e.gap if e.gap > 0 else 0.0)
                 for e in mill.elements}
    else:
        unknown = set(gaps) - set(mill.element_ids)
        if unknown:
            raise ValueError(f"gaps names unknown elements {sorted(unknown)}")
        drawn = {e.id: float(gaps.get(e.id, e.gap)) for e in mill.elements}
    fl = tuple(floating) if floating is not None else floating_elements(mill)
    fl = tuple(eid for eid in fl if drawn[eid] > 0)
    rate = float(rate_hz) if rate_hz is not None else float(rng.choice(RECORD_RATES_HZ))
    decim = sim_rate_hz / rate
    if abs(decim - round(decim)) > 1e-9:
        raise ValueError(f"sim_rate_hz {sim_rate_hz} is not a multiple of rate {rate}")
    decim = int(round(decim))
    friction = _draw_friction(mill, rng, fl, level0)
    t_first = float(first_bite_s) if first_bite_s is not None else float(rng.uniform(1.0, 2.5))
    bars = _draw_bars(rng, n_bars, level0, t_first, drawn, fl)
    last = bars[-1]
    duration = last.release.t_start + last.release.duration + last.idle_after
    aa = _draw_antialias(rng, decim)
    mean_level = float(np.mean([b.level for b in bars]))
    fractions = _static_torques(tree, tree.share)
    el_index = {e.id: j for j, e in enumerate(mill.elements)}
    chans = []
    for c in _torque_channels(mill):
        e = mill.element(c.element)
        lvl = max(abs(fractions[el_index[e.id]]), 0.05) * mean_level * e.ratio
        chans.append(_draw_channel(rng, c.name, lvl / _unit_factor(c.unit)))
    t0_ns = _EPOCH_NS + int(rng.integers(0, 365 * 86400 * 1000)) * 1_000_000
    draw = PlantDraw(mill=mill.name, gaps=drawn, floating=fl, friction=friction, bars=bars,
                     sim_rate_hz=float(sim_rate_hz), rate_hz=rate,
                     decim_phase=int(rng.integers(decim)), duration=float(duration),
                     antialias=aa, channels=tuple(chans), t0_ns=t0_ns,
                     noise_seed=int(rng.integers(2**63)),
                     block_s=float(rng.choice([0.05, 0.1, 0.2, 0.5])))
    cl = _draw_clearances(mill, rng, clearances)
    accel = None
    if accelerometers and cl and mill.acceleration_channels():
        accel = _draw_accel(mill, rng, draw.bearing_rate_hz, accel_rate_hz)
    return dataclasses.replace(draw, clearances=cl, accel=accel)


def _draw_clearances(mill: Mill, rng: np.random.Generator,
                     given: Mapping[str, float] | None) -> dict[str, float]:
    given = dict(given or {})
    unknown = set(given) - {b.id for b in mill.bearings}
    if unknown:
        raise ValueError(f"clearances names unknown bearings {sorted(unknown)}")
    return {b.id: float(given[b.id]) if b.id in given else
            _log_uniform(rng, 0.5, 10.0) * b.clearance for b in mill.bearings}


def _draw_accel(mill: Mill, rng: np.random.Generator, bearing_rate: float,
                rate_hz: float | None) -> AccelDraw:
    rate = float(rate_hz) if rate_hz is not None else float(rng.choice(ACCEL_RATES_HZ))
    decim = bearing_rate / rate
    if abs(decim - round(decim)) > 1e-9:
        raise ValueError(f"the bearing model's rate {bearing_rate} is not a multiple of the "
                         f"accelerometer rate {rate}")
    chans = tuple(AccelChannel(c.name, _log_uniform(rng, 0.001, 0.01),
                               float(rng.uniform(0.0, 0.3)), float(rng.uniform(-0.002, 0.002)))
                  for c in mill.acceleration_channels())
    return AccelDraw(rate_hz=rate, t_offset=round(float(rng.uniform(0.0, 0.05)), 4),
                     antialias=_draw_antialias(rng, int(round(decim))),
                     highpass_hz=_log_uniform(rng, 0.5, 3.0), channels=chans,
                     block_s=float(rng.choice([0.05, 0.1, 0.2])))


def _torque_channels(mill: Mill):
    out = []
    for c in mill.channels:
        if c.quantity is Quantity.TORQUE:
            out.append(c)
    if not out:
        raise ValueError(f"{mill.name} maps no torque channel")
    return out


# ==== load ===============================================================================
def load_profile(draw: PlantDraw, t: np.ndarray) -> np.ndarray:
    """Total rolling torque (N*m reduced) at simulation times ``t``."""
    L = np.zeros_like(t, dtype=float)
    for bar in draw.bars:
        t0 = bar.bite.t_start
        t1 = bar.release.t_start + bar.release.duration
        m = (t >= t0) & (t <= t1)
        if not m.any():
            continue
        tt = t[m]
        env = (bar.bite.shape((tt - t0) / bar.bite.duration)
               * (1.0 - bar.release.shape((tt - bar.release.t_start) / bar.release.duration)))
        L[m] += env * _bar_level(bar, tt)
    return L


def _bar_level(bar: Bar, t: np.ndarray, *, fluct: bool = True) -> np.ndarray:
    """The bar's rolling level (no ramps) at times ``t``: level, trend, fluctuation."""
    t0 = bar.bite.t_start
    span = bar.release.t_start - t0
    rel = 1.0 + bar.trend * (t - t0) / span
    if fluct:
        for amp, f, ph in bar.fluct:
            rel = rel + amp * np.sin(2 * math.pi * f * (t - t0) + ph)
    return bar.level * rel


# ==== the system =========================================================================
@dataclass(frozen=True)
class _System:
    tree: _Tree
    chars: tuple[_Char, ...]
    c: np.ndarray                 # (E,)
    friction: np.ndarray          # (n,) torque opposing rotation
    kp: float
    ki: float
    lim: float | None
    R: np.ndarray                 # (rows, N+3): mode test rows
    thr: np.ndarray               # (rows,)
    N: int


def _system(mill: Mill, draw: PlantDraw) -> _System:
    tree = _tree(mill)
    n, E = len(tree.ids), len(mill.elements)
    N = 2 * n + 1
    chars = tuple(_characteristic(e, draw.gaps[e.id]) for e in mill.elements)
    fric = np.zeros(n)
    for m, f in draw.friction.items():
        fric[tree.ids.index(m)] += f
    rows, thr = [], []
    for j, ch in enumerate(chars):
        for p in ch.bp:
            r = np.zeros(N + 3)
            r[tree.fr[j]] += 1.0
            r[tree.to[j]] -= 1.0
            rows.append(r)
            thr.append(p)
    lim = mill.motor.torque_limit
    if lim is not None:
        r = np.zeros(N + 3)
        r[n + tree.motor] = -mill.motor.kp
        r[2 * n] = mill.motor.ki
        rows += [r, -r]
        thr += [lim, lim]
    R = np.array(rows) if rows else np.zeros((0, N + 3))
    return _System(tree=tree, chars=chars, c=np.array([e.c for e in mill.elements]),
                   friction=fric, kp=mill.motor.kp, ki=mill.motor.ki, lim=lim, R=R,
                   thr=np.array(thr, dtype=float), N=N)


def _mode_map(sys: _System, w: np.ndarray, h: float) -> np.ndarray:
    """``[Phi | G]`` (N x N+3) of the mode the augmented state ``w`` is in."""
    tree = sys.tree
    n, N = len(tree.ids), sys.N
    E = len(sys.chars)
    A = np.zeros((E, n))
    A[np.arange(E), tree.fr] += 1.0
    A[np.arange(E), tree.to] -= 1.0
    d = A @ w[:n]
    s = np.empty(E)
    q = np.empty(E)
    for j, ch in enumerate(sys.chars):
        i = int(np.searchsorted(np.asarray(ch.bp, dtype=float), d[j], side="left"))
        s[j], q[j] = ch.slope[i], ch.icpt[i]
    m = tree.motor
    t_lin = -sys.kp * w[n + m] + sys.ki * w[2 * n]
    clamp = 0 if sys.lim is None or abs(t_lin) <= sys.lim else (1 if t_lin > 0 else -1)
    Jinv = 1.0 / tree.J
    M = np.zeros((N + 3, N + 3))
    M[:n, n:2 * n] = np.eye(n)
    M[n:2 * n, :n] = -Jinv[:, None] * (A.T @ (s[:, None] * A))
    M[n:2 * n, n:2 * n] = -Jinv[:, None] * (A.T @ (sys.c[:, None] * A))
    affine = -(A.T @ q) - sys.friction
    if clamp == 0:
        M[n + m, n + m] -= sys.kp * Jinv[m]
        M[n + m, 2 * n] += sys.ki * Jinv[m]
    else:
        affine[m] += clamp * sys.lim
    M[2 * n, n + m] = -1.0
    M[n:2 * n, N] = -tree.share * Jinv            # load L
    M[n:2 * n, N + 2] = affine * Jinv            # constant
    M[N, N + 1] = 1.0                             # L' = dL/dt
    Phi = linalg.expm(M * h)
    out = np.empty((N, N + 3))
    out[:, :N] = Phi[:N, :N]
    out[:, N] = Phi[:N, N]
    out[:, N + 1] = Phi[:N, N + 1] / h            # per unit of (L_k+1 - L_k)
    out[:, N + 2] = Phi[:N, N + 2]
    return out


def _reposition(sys: _System, x: np.ndarray, mill: Mill, targets: Mapping[str, float]) -> None:
    """Move the masses beyond each floating element so that its open part is ``targets[id]``."""
    tree = sys.tree
    n = len(tree.ids)
    for j, e in enumerate(mill.elements):
        if e.id not in targets:
            continue
        ch = sys.chars[j]
        d = x[tree.fr[j]] - x[tree.to[j]]
        shift = d - (ch.hi - targets[e.id])
        side = list(tree.away[j])
        near = tree.fr[j] if tree.away_is_to[j] else tree.to[j]
        x[side] += shift if tree.away_is_to[j] else -shift
        x[[n + i for i in side]] = x[n + near]


def _initial_state(sys: _System, mill: Mill, opens: Mapping[str, float]) -> np.ndarray:
    """Steady state at the nominal speed under idle friction, floating gaps at ``opens``."""
    tree = sys.tree
    n = len(tree.ids)
    T = _static_torques(tree, sys.friction)
    phi = np.zeros(n)
    for j, known, unknown in tree.order:
        e = mill.elements[j]
        ch = sys.chars[j]
        if e.id in opens:
            if abs(T[j]) > 1e-9 * max(1.0, float(np.abs(T).max())):
                raise ValueError(f"floating element {e.id} carries idle torque {T[j]}")
            d = ch.hi - opens[e.id]
        else:
            d = _g_inverse(ch, float(T[j]))
        phi[unknown] = phi[known] - d if unknown == tree.to[j] else phi[known] + d
    x = np.zeros(sys.N)
    x[:n] = phi
    x[2 * n] = float(sys.friction.sum()) / sys.ki
    return x


def _integrate(sys: _System, x0: np.ndarray, L: np.ndarray, h: float,
               events: Mapping[int, Callable[[np.ndarray], None]]) -> np.ndarray:
    """States at every step (rows), with ``events[k](x)`` applied to the state of step ``k``."""
    N = sys.N
    steps = L.size - 1
    X = np.empty((steps + 1, N + 3))
    X[:, N] = L
    X[:-1, N + 1] = np.diff(L)
    X[-1, N + 1] = 0.0
    X[:, N + 2] = 1.0
    X[0, :N] = x0
    R, thr = sys.R, sys.thr
    cache: dict[bytes, np.ndarray] = {}
    get = cache.get
    for k in range(steps):
        w = X[k]
        if k in events:
            events[k](w)
        key = (R @ w > thr).tobytes()
        P = get(key)
        if P is None:
            P = cache[key] = _mode_map(sys, w, h)
        X[k + 1, :N] = P @ w
    return X[:, :N]


def _element_torques(sys: _System, X: np.ndarray) -> np.ndarray:
    """Reduced torque ``g + c * d(delta)/dt`` of every element (E x steps)."""
    tree = sys.tree
    n = len(tree.ids)
    d = X[:, tree.fr] - X[:, tree.to]
    dd = X[:, n + tree.fr] - X[:, n + tree.to]
    out = np.empty((len(sys.chars), X.shape[0]))
    for j, ch in enumerate(sys.chars):
        out[j] = _g(ch, d[:, j]) + sys.c[j] * dd[:, j]
    return out


# ==== bearings: the radial model (mill-config.md), a small C kernel ========================
_BEARING_C = r"""/* validation.plantsim: radial bearing model, fixed-step RK4 (see plantsim.py) */
#include <math.h>
typedef struct { double ms, mh, kb, cb, cl, kh, kho, pre, ch, sa, ca, g; } P;
static void rhs(const P *p, const double *x, double F, double *dx) {
    double rx = x[0] - x[2], ry = x[1] - x[3];
    double r = sqrt(rx * rx + ry * ry), pen = r - p->cl, fcx = 0.0, fcy = 0.0;
    if (pen > 0.0) {
        double nx = rx / r, ny = ry / r;
        double f = p->kb * pen + p->cb * ((x[4] - x[6]) * nx + (x[5] - x[7]) * ny);
        if (f > 0.0) { fcx = -f * nx; fcy = -f * ny; }
    }
    double u = sqrt(x[2] * x[2] + x[3] * x[3]), u0 = p->pre / p->kh;
    double s = (u <= u0) ? p->kh * u : p->pre + p->kho * (u - u0);
    double fhx = -p->ch * x[6], fhy = -p->ch * x[7];
    if (u > 0.0) { fhx -= s * x[2] / u; fhy -= s * x[3] / u; }
    dx[0] = x[4]; dx[1] = x[5]; dx[2] = x[6]; dx[3] = x[7];
    dx[4] = (fcx + F * p->sa) / p->ms;
    dx[5] = (fcy + F * p->ca) / p->ms - p->g;
    dx[6] = (fhx - fcx) / p->mh;
    dx[7] = (fhy - fcy) / p->mh;
}
void plantsim_bearings(int nb, long n, double h, const double *F, const double *par,
                       double *x0, double *A) {
    for (int b = 0; b < nb; b++) {
        P p;
        const double *q = par + 12 * b;
        p.ms = q[0]; p.mh = q[1]; p.kb = q[2]; p.cb = q[3]; p.cl = q[4]; p.kh = q[5];
        p.kho = q[6]; p.pre = q[7]; p.ch = q[8]; p.sa = q[9]; p.ca = q[10]; p.g = q[11];
        const double *f = F + (long)b * n;
        double *a = A + (long)b * n * 2, *x = x0 + 8 * b;
        double k1[8], k2[8], k3[8], k4[8], y[8];
        for (long k = 0; k < n; k++) {
            rhs(&p, x, f[k], k1);
            a[2 * k] = k1[6]; a[2 * k + 1] = k1[7];
            if (k == n - 1) break;
            double fm = 0.5 * (f[k] + f[k + 1]);
            for (int i = 0; i < 8; i++) y[i] = x[i] + 0.5 * h * k1[i];
            rhs(&p, y, fm, k2);
            for (int i = 0; i < 8; i++) y[i] = x[i] + 0.5 * h * k2[i];
            rhs(&p, y, fm, k3);
            for (int i = 0; i < 8; i++) y[i] = x[i] + h * k3[i];
            rhs(&p, y, f[k + 1], k4);
            for (int i = 0; i < 8; i++) x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
    }
}
"""


class BearingKernelError(RuntimeError):
    """The C kernel of the bearing model could not be built (no C compiler)."""


def _bearing_kernel() -> Callable:
    """The compiled bearing integrator, built with ``cc`` on first use.

    The shared object is cached under the temporary directory, keyed by the hash of its
    source; it is built under a unique name and renamed into place.
    """
    import ctypes
    import hashlib
    import os
    import subprocess
    import tempfile

    tag = hashlib.sha256(_BEARING_C.encode()).hexdigest()[:16]
    folder = Path(tempfile.gettempdir()) / f"plantsim-{os.getuid()}"
    so = folder / f"bearings-{tag}.so"
    if not so.exists():
        folder.mkdir(parents=True, exist_ok=True)
        c_file = folder / f".bearings-{tag}-{os.getpid()}.c"
        tmp = folder / f".bearings-{tag}-{os.getpid()}.so"
        c_file.write_text(_BEARING_C)
        try:
            subprocess.run([os.environ.get("CC", "cc"), "-O2", "-shared", "-fPIC", "-o", str(tmp),
                            str(c_file), "-lm"], check=True, capture_output=True, timeout=120)
            os.replace(tmp, so)
        except (OSError, subprocess.SubprocessError) as exc:
            raise BearingKernelError(f"cannot compile the bearing kernel: {exc}") from None
        finally:
            c_file.unlink(missing_ok=True)
            tmp.unlink(missing_ok=True)
    lib = ctypes.CDLL(str(so))
    arr = np.ctypeslib.ndpointer(dtype=np.float64, flags="C_CONTIGUOUS")
    fn = lib.plantsim_bearings
    fn.argtypes = [ctypes.c_int, ctypes.c_long, ctypes.c_double, arr, arr, arr, arr]
    fn.restype = None
    return fn


def _bearing_params(b, clearance: float) -> list[float]:
    a = math.radians(b.pressure_angle_deg)
    k_open = b.k_housing_open if b.k_housing_open is not None else b.k_housing
    return [b.shaft_mass, b.housing_mass, b.k_bearing, b.c_bearing, clearance, b.k_housing,
            k_open, b.housing_preload, b.c_housing, math.sin(a), math.cos(a), G0]


def _bearing_static(par: Sequence[float], force: float) -> list[float]:
    """Static state [x_s, y_s, x_h, y_h, 0, 0, 0, 0] under mesh force ``force`` and gravity."""
    ms, _, kb, _, cl, kh, kho, pre, _, sa, ca, g = par
    fx, fy = force * sa, force * ca - ms * g
    f = math.hypot(fx, fy)
    if f == 0.0:
        return [0.0] * 8
    nx, ny = fx / f, fy / f
    u = f / kh if f <= pre else pre / kh + (f - pre) / kho
    r = cl + f / kb
    return [nx * (u + r), ny * (u + r), nx * u, ny * u, 0.0, 0.0, 0.0, 0.0]


def _housing_accels(mill: Mill, draw: PlantDraw, tau: np.ndarray, fs: float,
                    n: int) -> np.ndarray:
    """Housing accelerations (bearings x n x [horizontal, vertical]), m/s^2, at 5 x ``fs``.

    Radial model of mill-config.md per bearing: shaft and housing point masses in the
    plane; the whole mesh force ``T_mesh * ratio / base_radius`` on the shaft along the
    line of action (``pressure_angle_deg`` from the vertical, up and towards +horizontal
    for positive torque), gravity on the shaft; shaft-housing contact beyond the radial
    clearance (``k_bearing``, ``c_bearing`` while in contact, no pull); housing on an
    isotropic bilinear spring (``k_housing`` up to ``housing_preload``, ``k_housing_open``
    beyond) with ``c_housing``.  Fixed-step RK4, the mesh force linear between torsional
    samples.  Starts from the static state; no feedback into the torsion.
    """
    fb = BEARING_OVERSAMPLE * fs
    t_sim = np.arange(tau.shape[1]) / fs
    tb = np.arange(n) / fb
    el = {e.id: j for j, e in enumerate(mill.elements)}
    forces, pars, x0 = [], [], []
    for b in mill.bearings:
        f = np.interp(tb, t_sim, tau[el[b.mesh]]) * b.ratio / b.base_radius
        par = _bearing_params(b, draw.clearances[b.id])
        forces.append(f)
        pars.append(par)
        x0.append(_bearing_static(par, float(f[0])))
    out = np.zeros((len(forces), n, 2))
    _bearing_kernel()(len(forces), n, 1.0 / fb, np.ascontiguousarray(forces),
                      np.ascontiguousarray(pars, dtype=float),
                      np.ascontiguousarray(x0, dtype=float), out)
    return out


# ==== recording chain ====================================================================
def _filter_design(aa: AntiAlias, fs: float, rate: float) -> tuple[str, Any, int]:
    """(kind, coefficients, delay compensated in simulation samples)."""
    fc = aa.cutoff * rate
    if aa.kind == "fir":
        win: Any = ("kaiser", aa.kaiser_beta) if aa.window == "kaiser" else aa.window
        b = signal.firwin(aa.numtaps, fc, window=win, fs=fs)
        return "fir", b, (aa.numtaps - 1) // 2 if aa.compensated else 0
    if aa.kind == "butter":
        sos = signal.butter(aa.order, fc, fs=fs, output="sos")
    else:
        sos = signal.cheby1(aa.order, aa.ripple_db, fc, fs=fs, output="sos")
    _, hdc = signal.sosfreqz(sos, worN=[0.0], fs=fs)
    sos = sos.copy()
    sos[0, :3] /= float(np.real(hdc[0]))
    return "sos", sos, 0


def _impulse(kind: str, coef: Any, n: int) -> np.ndarray:
    if kind == "fir":
        return np.asarray(coef)
    x = np.zeros(n)
    x[0] = 1.0
    return signal.sosfilt(coef, x)


def _apply_filter(kind: str, coef: Any, x: np.ndarray) -> np.ndarray:
    """Filter rows of ``x`` causally, starting from the steady state of their first values."""
    if kind == "fir":
        zi = signal.lfilter_zi(coef, [1.0])
        return signal.lfilter(coef, [1.0], x, axis=1, zi=zi[None, :] * x[:, :1])[0]
    zi = signal.sosfilt_zi(coef)[:, None, :] * x[None, :, 0:1]
    return signal.sosfilt(coef, x, axis=1, zi=zi)[0]


def _round_full_scale(peak: float) -> float:
    """Smallest 1, 2, 5 x 10^k that is at least ``2 * peak``."""
    need = 2.0 * max(peak, 1e-30)
    k = math.floor(math.log10(need))
    for base in (1.0, 2.0, 5.0, 10.0):
        fs = base * 10.0 ** k
        if fs >= need * (1 - 1e-12):
            return float(fs)
    return 10.0 ** (k + 1)


def _quantise(x: np.ndarray, full_scale: float) -> np.ndarray:
    q = full_scale / 65536.0
    return np.clip(np.round(x / q), -32768, 32767) * q


# ==== the recording ======================================================================
@dataclass(frozen=True)
class PlantDevice:
    """A further recorded device (the accelerometer conditioner).

    ``t_offset`` is its first sample's time from the recording's first (torque) sample, s;
    ``data`` as recorded (quantised) and ``clean`` (no noise, offset or quantisation), in
    ``units``, shape (n_channels, n_samples).
    """

    name: str
    rate_hz: float
    t_offset: float
    channels: tuple[str, ...]
    units: tuple[str, ...]
    data: np.ndarray
    clean: np.ndarray

    @property
    def time(self) -> np.ndarray:
        """Sample times, s from the recording's first sample."""
        return self.t_offset + np.arange(self.data.shape[1]) / self.rate_hz


@dataclass(frozen=True)
class PlantRecording:
    """One generated recording.

    Attributes
    ----------
    mill : str
    rate_hz : float
    t0_ns : int
        First sample, ns since the Unix epoch.
    channels, units : tuple of str
    data : ndarray (n_channels, n_samples)
        As recorded (quantised), in ``units``.
    clean : ndarray (n_channels, n_samples)
        The same chain without noise, offset, drift and quantisation (filter and
        decimation only), in ``units``.
    sim_rate_hz : float
    physics : ndarray (n_channels, n_sim)
        Physical shaft torque of each channel's element at the simulation rate, N*m.
    load : ndarray (n_sim,)
        Total rolling torque, N*m reduced.
    sim_t_offset : float
        Time of physics sample 0 relative to the first recorded sample, s (<= 0).
    truth : dict
        What the truth sidecar holds.
    accel : PlantDevice or None
        The accelerometers, when the draw has them.
    """

    mill: str
    rate_hz: float
    t0_ns: int
    channels: tuple[str, ...]
    units: tuple[str, ...]
    data: np.ndarray
    clean: np.ndarray
    sim_rate_hz: float
    physics: np.ndarray
    load: np.ndarray
    sim_t_offset: float
    truth: dict = field(repr=False)
    accel: PlantDevice | None = None

    @property
    def time(self) -> np.ndarray:
        """Recorded sample times, s from the first sample."""
        return np.arange(self.data.shape[1]) / self.rate_hz


def _events(sys: _System, mill: Mill, draw: PlantDraw, fs: float) -> dict[int, Callable]:
    out: dict[int, Callable] = {}
    for bar in draw.bars:
        if bar.t_reposition is None or not bar.gap_open:
            continue
        k = int(round(bar.t_reposition * fs))
        out[k] = (lambda x, opens=dict(bar.gap_open): _reposition(sys, x, mill, opens))
    return out


def _gap_open_at(sys: _System, mill: Mill, X: np.ndarray, k: int) -> dict[str, dict[str, float]]:
    tree = sys.tree
    out = {}
    for j, e in enumerate(mill.elements):
        d = float(X[k, tree.fr[j]] - X[k, tree.to[j]])
        signed = sys.chars[j].hi - d
        width = sys.chars[j].hi - sys.chars[j].lo
        out[e.id] = {"gap_open": max(0.0, min(signed, width)), "signed": signed}
    return out


def _nearest_channels(mill: Mill) -> list[str]:
    """Torque channels nearest the rolls (ties all returned), those with a static load."""
    frac = load_fractions(mill)
    dist = _distance_to_load(mill)
    cands = [c for c in _torque_channels(mill) if abs(frac[c.element]) > 0.05]
    dmin = min(dist[c.element] for c in cands)
    return [c.name for c in cands if dist[c.element] == dmin]


def _half_height(x: np.ndarray, t: np.ndarray, i0: int, half: float, up: bool) -> float:
    """First time after sample ``i0`` that ``x`` crosses ``half`` (linear interpolation)."""
    seg = x[i0:] - half
    hit = np.flatnonzero(seg >= 0) if up else np.flatnonzero(seg <= 0)
    if hit.size == 0:
        return math.nan
    i = int(hit[0]) + i0
    if i == 0:
        return float(t[0])
    a, b = x[i - 1] - half, x[i] - half
    frac = a / (a - b) if a != b else 0.0
    return float(t[i - 1] + frac * (t[i] - t[i - 1]))


def _idle_estimate(mill: Mill, sys: _System, near: Sequence[str]) -> float:
    """Static total-load estimate of the nearest channels under idle friction alone."""
    frac = load_fractions(mill)
    T = _static_torques(sys.tree, sys.friction)
    el = {e.id: j for j, e in enumerate(mill.elements)}
    vals = [T[el[mill.channel(c).element]] / frac[mill.channel(c).element] for c in near]
    return float(np.mean(vals))


def _steps_truth(mill: Mill, draw: PlantDraw, sys: _System, X: np.ndarray, clean: np.ndarray,
                 names: Sequence[str], fs: float) -> list[dict[str, Any]]:
    """Every load step: kind, t_step (half height of the noise-free recorded torque), levels."""
    frac = load_fractions(mill)
    near = _nearest_channels(mill)
    rows = [names.index(c) for c in near]
    est = np.zeros(clean.shape[1])
    for i, c in zip(rows, near):
        ch = mill.channel(c)
        e = mill.element(ch.element)
        est += clean[i] * _unit_factor(ch.unit) / e.ratio / frac[e.id]
    est /= len(rows)
    t_rec = np.arange(clean.shape[1]) / draw.rate_hz
    t_shift = draw.t_rec0
    base = _idle_estimate(mill, sys, near)
    out = []
    for b, bar in enumerate(draw.bars):
        for kind, ramp in (("bite", bar.bite), ("release", bar.release)):
            half_t = ramp.half_time()
            level = float(_bar_level(bar, np.array([half_t]), fluct=False)[0])
            at = ramp.t_start + ramp.duration if kind == "bite" else ramp.t_start
            lvl_fl = float(_bar_level(bar, np.array([at]))[0])
            before, after = (0.0, lvl_fl) if kind == "bite" else (lvl_fl, 0.0)
            i0 = max(0, int(math.floor((ramp.t_start - t_shift) * draw.rate_hz)))
            half = base + 0.5 * (before + after)
            ts = _half_height(est, t_rec, i0, half, up=kind == "bite")
            opens = _gap_open_at(sys, mill, X, int(round(ramp.t_start * fs)))
            out.append({"kind": kind, "bar": b, "t_step": ts,
                        "t_load_start": ramp.t_start - t_shift,
                        "t_load_half": half_t - t_shift,
                        "rise_s": ramp.duration, "shape": ramp.kind,
                        "static_torque": level, "step": level if kind == "bite" else -level,
                        "load_before": before, "load_after": after,
                        "gap_open": {eid: v["gap_open"] for eid, v in opens.items()},
                        "gap_open_signed": {eid: v["signed"] for eid, v in opens.items()}})
    return out


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _chain(fs: float, rate: float, phase: int, aa: AntiAlias, x: np.ndarray, n_rec: int,
           rng: np.random.Generator,
           nuisance: Callable[[np.ndarray], Sequence[ChannelNuisance]],
           highpass_hz: float | None = None
           ) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]], dict[str, Any]]:
    """Recorded and noise-free recorded samples of every row of ``x`` (at ``fs``).

    ``nuisance(clean)`` gives each channel's nuisance (absolute, in its unit) from the
    noise-free recorded samples; the first recorded sample is simulation sample ``phase``.
    """
    M = int(round(fs / rate))
    kind, coef, comp = _filter_design(aa, fs, rate)
    if highpass_hz is not None:      # the sensor's AC coupling, before its noise
        x = _apply_filter("sos", signal.butter(1, highpass_hz, "highpass", fs=fs,
                                               output="sos"), x)
    h = _impulse(kind, coef, int(fs))
    gain2 = float(np.sum(h ** 2))
    delay_s = float(np.sum(np.arange(h.size) * h) / np.sum(h)) / fs - comp / fs
    idx = phase + comp + M * np.arange(n_rec)
    clean = _apply_filter(kind, coef, x)[:, idx]
    chans = nuisance(clean)
    sig_tot = np.array([c.noise_frac * c.level for c in chans])
    post = np.array([c.post_share for c in chans])
    sig_pre = np.sqrt(1.0 - post) * sig_tot / math.sqrt(gain2)
    sig_post = np.sqrt(post) * sig_tot
    noisy = x + sig_pre[:, None] * rng.standard_normal(x.shape)
    rec = _apply_filter(kind, coef, noisy)[:, idx]
    rec += sig_post[:, None] * rng.standard_normal(rec.shape)
    t = np.arange(n_rec) / rate
    T = n_rec / rate
    info = []
    for i, c in enumerate(chans):
        walk = np.cumsum(rng.standard_normal(n_rec)) * (c.walk_end_std / math.sqrt(n_rec))
        rec[i] += (c.offset + c.drift_linear * t / T
                   + c.drift_sine * np.sin(2 * math.pi * c.drift_freq * t + c.drift_phase) + walk)
        fsc = _round_full_scale(float(np.max(np.abs(rec[i]))))
        rec[i] = _quantise(rec[i], fsc)
        q = fsc / 65536.0
        info.append({"full_scale": fsc, "quant_step": q, "sigma_pre_filter": float(sig_pre[i]),
                     "sigma_post": float(sig_post[i]), "sigma": float(sig_tot[i]),
                     "sigma_with_quantisation": float(math.sqrt(sig_tot[i] ** 2 + q * q / 12)),
                     "level": c.level, "offset": c.offset, "drift_linear": c.drift_linear,
                     "drift_sine": c.drift_sine, "drift_freq_hz": c.drift_freq,
                     "walk_end_std": c.walk_end_std})
    chain = {"antialias": _jsonable(aa), "decimation": M, "noise_gain": gain2,
             "delay_s": delay_s, "delay_compensated_samples": comp,
             "highpass_hz": highpass_hz}
    return rec, clean, info, chain


def simulate_plant(mill: Mill, draw: PlantDraw, *, rate_hz: float | None = None) -> PlantRecording:
    """Simulate the physics and the recording chain of one drawn recording.

    Parameters
    ----------
    mill : Mill
        The stand the draw was made for.
    draw : PlantDraw
        From :func:`draw_plant`.
    rate_hz : float, optional
        Physics (integration) rate overriding ``draw.sim_rate_hz``; must be an integer
        multiple of the recorded rate (used by the step-halving check).

    Returns
    -------
    PlantRecording
        Recorded samples, noise-free chain output, the physics and the truth.
    """
    if draw.mill != mill.name:
        raise ValueError(f"the draw is for mill {draw.mill!r}, not {mill.name!r}")
    if rate_hz is not None:
        draw = _with_sim_rate(draw, float(rate_hz))
    fs = draw.sim_rate_hz
    M = int(round(fs / draw.rate_hz))
    sys = _system(mill, draw)
    n_rec = int(math.floor((draw.duration - draw.t_rec0) * draw.rate_hz))
    kind, coef, comp = _filter_design(draw.antialias, fs, draw.rate_hz)
    n_sim = draw.decim_phase + comp + M * (n_rec - 1) + 1
    t = np.arange(n_sim) / fs
    L = load_profile(draw, t)
    x0 = _initial_state(sys, mill, draw.bars[0].gap_open)
    X = _integrate(sys, x0, L, 1.0 / fs, _events(sys, mill, draw, fs))
    tau = _element_torques(sys, X)
    chans = _torque_channels(mill)
    el = {e.id: j for j, e in enumerate(mill.elements)}
    physics = np.array([tau[el[c.element]] * mill.element(c.element).ratio for c in chans])
    factors = np.array([_unit_factor(c.unit) for c in chans])
    rec, clean, info, chain = _chain(fs, draw.rate_hz, draw.decim_phase, draw.antialias,
                                     physics / factors[:, None], n_rec,
                                     np.random.default_rng(draw.noise_seed),
                                     lambda _clean: draw.channels)
    names = [c.name for c in chans]
    truth = _truth(mill, draw, sys, X, clean, names, info, chain, fs)
    accel = None
    if draw.accel is not None:
        try:
            accel, accel_truth = _simulate_accel(mill, draw, tau)
        except BearingKernelError as exc:
            warnings.warn(f"plantsim: no accelerometers: {exc}", RuntimeWarning, stacklevel=2)
            accel_truth = {"accel": {"skipped": str(exc)}}
        truth = _merge_accel_truth(truth, accel_truth)
    return PlantRecording(mill=mill.name, rate_hz=draw.rate_hz, t0_ns=draw.t0_ns,
                          channels=tuple(names), units=tuple(c.unit for c in chans),
                          data=rec, clean=clean, sim_rate_hz=fs, physics=physics, load=L,
                          sim_t_offset=-draw.t_rec0, truth=truth, accel=accel)


def _scaled_antialias(aa: AntiAlias, scale: float) -> AntiAlias:
    if aa.kind != "fir":
        return aa
    return dataclasses.replace(aa, numtaps=2 * int(round((aa.numtaps - 1) / 2 * scale)) + 1)


def _with_sim_rate(draw: PlantDraw, rate_hz: float) -> PlantDraw:
    """The same draw integrated at another physics rate (FIR lengths kept in seconds)."""
    M = rate_hz / draw.rate_hz
    if abs(M - round(M)) > 1e-9:
        raise ValueError(f"rate_hz {rate_hz} is not a multiple of the recorded rate "
                         f"{draw.rate_hz}")
    scale = rate_hz / draw.sim_rate_hz
    accel = draw.accel
    if accel is not None:
        Mb = BEARING_OVERSAMPLE * rate_hz / accel.rate_hz
        if abs(Mb - round(Mb)) > 1e-9:
            raise ValueError(f"rate_hz {rate_hz}: the bearing model's rate is not a multiple "
                             f"of the accelerometer rate {accel.rate_hz}")
        accel = dataclasses.replace(accel, antialias=_scaled_antialias(accel.antialias, scale))
    return dataclasses.replace(draw, sim_rate_hz=rate_hz,
                               decim_phase=int(round(draw.decim_phase * scale)),
                               antialias=_scaled_antialias(draw.antialias, scale), accel=accel)


def _simulate_accel(mill: Mill, draw: PlantDraw, tau: np.ndarray
                    ) -> tuple[PlantDevice, dict[str, Any]]:
    """The accelerometer device: radial model at 5 x the torsional rate, then its chain."""
    ad = draw.accel
    fs = draw.sim_rate_hz
    fb = BEARING_OVERSAMPLE * fs
    M = int(round(fb / ad.rate_hz))
    _, _, comp = _filter_design(ad.antialias, fb, ad.rate_hz)
    phase = int(round((draw.t_rec0 + ad.t_offset) * fb))
    last = (tau.shape[1] - 1) * BEARING_OVERSAMPLE
    n_rec = (last - phase - comp) // M + 1
    acc = _housing_accels(mill, draw, tau, fs, phase + comp + M * (n_rec - 1) + 1)
    bearing = {b.id: i for i, b in enumerate(mill.bearings)}
    chans = [c for c in mill.acceleration_channels() if c.bearing in bearing]
    x = np.array([acc[bearing[c.bearing], :, 1 if c.direction == "vertical" else 0]
                  / _accel_factor(c.unit) for c in chans])
    drawn = {a.name: a for a in ad.channels}

    def nuisance(clean: np.ndarray) -> list[ChannelNuisance]:
        out = []
        for i, c in enumerate(chans):
            a = drawn[c.name]
            lvl = float(np.percentile(np.abs(clean[i]), 99.9))
            out.append(ChannelNuisance(c.name, lvl, a.noise_frac, a.post_share,
                                       a.offset_frac * lvl, 0.0, 0.0, 0.0, 0.0, 0.0))
        return out

    rec, clean, info, chain = _chain(fb, ad.rate_hz, phase, ad.antialias, x, n_rec,
                                     np.random.default_rng([draw.noise_seed, 1]), nuisance,
                                     highpass_hz=ad.highpass_hz)
    t_off = phase / fb - draw.t_rec0
    dev = PlantDevice(_ACCEL_DEVICE, ad.rate_hz, t_off, tuple(c.name for c in chans),
                      tuple(c.unit for c in chans), rec, clean)
    channels = {}
    for i, c in enumerate(chans):
        channels[c.name] = {"device": _ACCEL_DEVICE, "unit": c.unit, "bearing": c.bearing,
                            "direction": c.direction, "sigma": info[i]["sigma"],
                            "sigma_si": info[i]["sigma"] * _accel_factor(c.unit),
                            **{k: v for k, v in info[i].items() if k != "sigma"}}
    bearings = {b.id: {"clearance": draw.clearances[b.id], "clearance_design": b.clearance,
                       "mesh": b.mesh} for b in mill.bearings}
    return dev, {"accel": {"rate_hz": ad.rate_hz, "t_offset": t_off, "sim_rate_hz": fb,
                           "n_samples": int(n_rec), "chain": chain},
                 "bearings": bearings, "channels": channels}


def _merge_accel_truth(truth: dict[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(truth)
    for k, v in extra.items():
        out[k] = {**out[k], **v} if k == "channels" else v
    return out


def _accel_factor(unit: str) -> float:
    try:
        return ACCEL_UNIT_TO_SI[unit]
    except KeyError:
        raise ValueError(f"plantsim writes acceleration in {sorted(ACCEL_UNIT_TO_SI)}; "
                         f"got {unit!r}") from None


def _truth(mill: Mill, draw: PlantDraw, sys: _System, X: np.ndarray, clean: np.ndarray,
           names: Sequence[str], info: list[dict], chain: dict, fs: float) -> dict[str, Any]:
    steps = _steps_truth(mill, draw, sys, X, clean, names, fs)
    elements = {}
    for j, e in enumerate(mill.elements):
        bites = [s for s in steps if s["kind"] == "bite"]
        elements[e.id] = {"gap": draw.gaps[e.id], "gap_design": e.gap,
                          "floating": e.id in draw.floating,
                          "drive_flank": sys.chars[j].hi, "back_flank": sys.chars[j].lo,
                          "gap_open": [s["gap_open"][e.id] for s in bites],
                          "gap_open_drawn": [b.gap_open.get(e.id) for b in draw.bars]}
    channels = {}
    for i, c in enumerate(draw.channels):
        ch = mill.channel(c.name)
        e = mill.element(ch.element)
        si = _unit_factor(ch.unit) / e.ratio
        channels[c.name] = {"device": _DEVICE, "unit": ch.unit, "element": ch.element,
                            "ratio": e.ratio,
                            "sigma": info[i]["sigma"], "sigma_si_reduced": info[i]["sigma"] * si,
                            **{k: v for k, v in info[i].items() if k != "sigma"},
                            "rolling_level": c.level}
    return {"generator": "validation.plantsim", "version": 1, "mill": mill.name,
            "rate_hz": draw.rate_hz, "sim_rate_hz": fs, "t0_ns": draw.t0_ns,
            "n_samples": int(clean.shape[1]), "duration_s": clean.shape[1] / draw.rate_hz,
            "time_origin": "t = 0 is the first recorded sample; load times are when the "
                           "load acts, t_step is in the recorded (filtered) torque",
            "nearest_channels": _nearest_channels(mill),
            "elements": elements, "steps": steps, "channels": channels, "chain": chain,
            "friction": dict(draw.friction), "draw": _jsonable(draw)}


# ==== files ==============================================================================
def truth_path(path: str | Path) -> Path:
    """The truth sidecar of a recording: ``name.csv`` -> ``name.truth.json``."""
    p = Path(path)
    return p.with_name(p.stem + ".truth.json")


def _devices(rec: PlantRecording) -> list[PlantDevice]:
    """Every device of a recording, the torque device first (at time 0)."""
    torque = PlantDevice(_DEVICE, rec.rate_hz, 0.0, rec.channels, rec.units, rec.data, rec.clean)
    return [torque] + ([rec.accel] if rec.accel is not None else [])


def accel_csv_path(path: str | Path) -> Path:
    """The accelerometer device's CSV beside ``name.csv``: ``name.accel.csv``."""
    p = Path(path)
    return p.with_name(f"{p.stem}.accel{p.suffix}")


def _write_csv_device(dev: PlantDevice, path: Path) -> None:
    header = ",".join(["time"] + [f"{c} [{u}]" for c, u in zip(dev.channels, dev.units)])
    cols = np.column_stack([dev.time] + [dev.data[i] for i in range(len(dev.channels))])
    fmt = ["%.7f"] + ["%.10g"] * len(dev.channels)
    with open(path, "w", encoding="ascii", newline="\n") as fh:
        np.savetxt(fh, cols, fmt=fmt, delimiter=",", header=header, comments="")


def _json_schema() -> bytes:
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema",
              "title": "ident.SampleBlock", "type": "object",
              "required": ["t0_ns", "rate_hz", "channels", "units", "data"],
              "properties": {"t0_ns": {"type": "integer"}, "rate_hz": {"type": "number"},
                             "channels": {"type": "array", "items": {"type": "string"}},
                             "units": {"type": "array", "items": {"type": "string"}},
                             "data": {"type": "array", "items": {
                                 "type": "array", "items": {"type": ["number", "null"]}}}}}
    return json.dumps(schema).encode()


def _write_mcap(rec: PlantRecording, path: Path, block_s: Sequence[float]) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="validation.plantsim")
        sid = w.register_schema(name="ident.SampleBlock", encoding="jsonschema",
                                data=_json_schema())
        w.add_metadata("ident.recording", {"mill": rec.mill,
                                           "recording_id": f"plantsim-{rec.t0_ns}"})
        for dev, bsec in zip(_devices(rec), block_s):
            cid = w.register_channel(topic=dev.name, message_encoding="json", schema_id=sid)
            t_dev = rec.t0_ns + int(round(dev.t_offset * 1e9))
            bs = max(1, int(round(bsec * dev.rate_hz)))
            for seq, start in enumerate(range(0, dev.data.shape[1], bs)):
                t0 = t_dev + int(round(start * 1e9 / dev.rate_hz))
                msg = {"t0_ns": t0, "rate_hz": dev.rate_hz, "channels": list(dev.channels),
                       "units": list(dev.units),
                       "data": dev.data[:, start:start + bs].tolist()}
                w.add_message(channel_id=cid, log_time=t0, publish_time=t0, sequence=seq,
                              data=json.dumps(msg, separators=(",", ":")).encode())
        w.finish()


def write_plant(rec: PlantRecording, path: str | Path) -> Path:
    """Write a recording (CSV or MCAP by extension) and its truth sidecar.

    CSV: ``time`` in float seconds from the first sample, headers ``name [unit]``, one
    rate per file (the accelerometers, when present, in ``name.accel.csv`` on the same
    time origin).  MCAP: topics ``/telemetry/torque`` and ``/telemetry/accel`` of JSON
    ``ident.SampleBlock`` messages (official ``mcap`` writer), ``ident.recording``
    metadata.  Returns the truth path.
    """
    p = Path(path)
    ext = p.suffix.lower()
    p.parent.mkdir(parents=True, exist_ok=True)
    draw = rec.truth.get("draw", {})
    if ext == ".csv":
        devices = _devices(rec)
        _write_csv_device(devices[0], p)
        if len(devices) > 1:
            _write_csv_device(devices[1], accel_csv_path(p))
    elif ext == ".mcap":
        blocks = [float(draw.get("block_s", 0.1)),
                  float((draw.get("accel") or {}).get("block_s", 0.1))]
        _write_mcap(rec, p, blocks)
    else:
        raise ValueError(f"unknown recording format {p.suffix!r}; expected .csv or .mcap")
    tp = truth_path(p)
    tp.write_text(json.dumps(_jsonable(rec.truth), indent=1) + "\n", encoding="utf-8")
    return tp


def make_recording(mill: Mill | str | Path, seed: int, path: str | Path, *,
                   gaps: Mapping[str, float] | None = None, n_bars: int = 2,
                   fmt: str = "csv") -> dict[str, Any]:
    """Draw, simulate and write one recording; returns its truth.

    ``path`` gets the extension ``fmt`` (``csv`` or ``mcap``) when it has none; a
    different extension is an error.  Deterministic given (mill, seed).
    """
    if not isinstance(mill, Mill):
        from ident import load_mill

        mill = load_mill(mill)
    p = Path(path)
    if fmt not in ("csv", "mcap"):
        raise ValueError(f"fmt must be 'csv' or 'mcap'; got {fmt!r}")
    if p.suffix == "":
        p = p.with_suffix("." + fmt)
    elif p.suffix.lower() != "." + fmt:
        raise ValueError(f"path {p} does not end in .{fmt}")
    draw = draw_plant(mill, np.random.default_rng(seed), gaps=gaps, n_bars=n_bars)
    rec = simulate_plant(mill, draw)
    truth = dict(rec.truth, seed=int(seed))
    rec = dataclasses.replace(rec, truth=truth)
    write_plant(rec, p)
    return truth
