"""Effects a mill file leaves out (``spec/effects.md``), as terms of the driveline model.

Each effect is a small frozen dataclass implementing the
:class:`~ident.model.dynamics.Effect` protocol: ``name`` (the effects.md name),
``location`` (an element, a spindle, a roll pair ``"Q6-Q7"`` or the motor
mass), ``param_names`` / ``param_defaults`` (the dataclass fields; the model
names them ``f"{name}@{location}.{param}"``) and ``terms(ctx, p)``.  Add them
with ``ModelOptions(effects=(SofteningStiffness("C46"), ...))``.

=====================  =========================================================
effect                 model term (reduced to the motor shaft, SI)
=====================  =========================================================
``backlash``           a dead zone of ``gap`` (``gap_open`` of it on the drive
                       side) added to the element's characteristic, seed Fig. 1a:
                       ``g1(d; a + gap - gap_open, b + gap_open) - g1(d; a, b)``
``softening_stiffness`` stiffness ``k_ratio * k`` (``k_ratio < 1``) beyond ``knee``
                       rad past contact on either side, seed Fig. 1b
``hardening_stiffness`` the same with ``k_ratio > 1``, seed Fig. 1c
``spindle_imbalance``  the open part of the spindle's gap swings with twice the
                       physical roll angle: ``b += amplitude * sin(2 phi + phase)``,
                       ``phi = (Omega t + theta_to) / ratio``
``coulomb_friction``   ``force * tanh(d(delta)/dt / v_smooth)`` across the element,
                       at all times; its torque channel reads it
``strip_coupling``     an element ``k, c`` between two roll masses
``torque_loop_lag``    ``T_motor' = (T_command - T_motor) / tau`` instead of an
                       ideal torque loop
=====================  =========================================================

Besides the protocol every effect gives :meth:`specs` (bounds, scales and
which parameters a refit frees, for a given mill), :meth:`neutral` (parameter
values that switch it off) and :meth:`static_states` (its extra states at rest
under a load).  :class:`Gated` multiplies any effect by a ``gate`` parameter in
[0, 1], so that one compiled model can hold several candidates switched off.

:class:`SensorFilter` is *not* a model term: it is a sensor-chain low-pass
applied to a recorded channel, outside the effects.md library (the
discrepancy workflow's out-of-library control).

Location kinds (:func:`candidate_locations`): ``backlash`` goes on elements the
mill file says are tight (``gap = 0``); stiffness and friction on any element;
``spindle_imbalance`` on a spindle (an element touching a load mass);
``strip_coupling`` on a pair of load masses; ``torque_loop_lag`` on the motor mass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import casadi as ca
import numpy as np

from ..description import Mill
from ..errors import IdentError
from . import laws
from .dynamics import EffectTerms

__all__ = ["EFFECT_NAMES", "ParamSpec", "Backlash", "SofteningStiffness", "HardeningStiffness",
           "SpindleImbalance", "CoulombFriction", "StripCoupling", "TorqueLoopLag", "Gated",
           "SensorFilter", "Drag", "make_effect", "candidate_locations", "spindles", "roll_pairs",
           "typical_deflection",
           "EFFECT_CLASSES"]

#: The effects.md names, in the table's order.
EFFECT_NAMES = ("backlash", "softening_stiffness", "hardening_stiffness", "spindle_imbalance",
                "coulomb_friction", "strip_coupling", "torque_loop_lag")


@dataclass(frozen=True)
class ParamSpec:
    """How a refit treats one effect parameter.

    Attributes
    ----------
    name : str
        Local parameter name (``knee``, ``force`` ...).
    lower, upper : float
        Bounds, in the parameter's unit.
    scale : float
        Typical magnitude (the optimiser works on ``value / scale``).
    free : bool
        Whether a refit adjusts it (otherwise it stays at the effect's value).
    """

    name: str
    lower: float
    upper: float
    scale: float
    free: bool = True


def _element_index(mill: Mill, element_id: str, effect: str) -> int:
    try:
        return mill.element_ids.index(element_id)
    except ValueError:
        raise IdentError(f"{effect}: location must be an element of mill '{mill.name}' "
                         f"({', '.join(mill.element_ids)}). Got {element_id!r}.") from None


def _smax(x: Any, w: Any) -> Any:
    return ca.fmax(x, 0) if w is None else laws.smooth_max(x, w, ca)


def _smin(x: Any, w: Any) -> Any:
    return ca.fmin(x, 0) if w is None else laws.smooth_min(x, w, ca)


def typical_deflection(mill: Mill, element_id: str, *, torque: float | None = None) -> float:
    """Static deflection beyond contact of an element under a rolling torque, rad.

    Parameters
    ----------
    mill : Mill
    element_id : str
    torque : float, optional
        Total rolling torque, N*m reduced (default :func:`~.scenario.nominal_torque`);
        the element carries its static share of it.
    """
    from .scenario import nominal_torque

    from ..segment.loadshare import load_fractions

    share = load_fractions(mill).get(element_id, 0.5)
    e = mill.element(element_id)
    t = nominal_torque(mill) if torque is None else abs(float(torque))
    return max(abs(share) * t / e.k, 1e-4)


class _Base:
    """Shared protocol plumbing: parameters are the dataclass's float fields."""

    name: ClassVar[str]
    _params: ClassVar[tuple[str, ...]]
    needs_history: ClassVar[bool] = False

    @property
    def param_names(self) -> tuple[str, ...]:
        return self._params

    @property
    def param_defaults(self) -> tuple[float, ...]:
        return tuple(float(getattr(self, n)) for n in self._params)

    @property
    def key(self) -> str:
        """``name@location``, the prefix of the effect's model parameters."""
        return f"{self.name}@{self.location}"  # type: ignore[attr-defined]

    def param_key(self, param: str) -> str:
        """Model parameter name of one of the effect's parameters."""
        return f"{self.key}.{param}"

    def neutral(self, mill: Mill) -> dict[str, float]:
        """Parameter values that switch the effect off (local names)."""
        raise NotImplementedError

    def static_states(self, mill: Mill, level: float) -> tuple[float, ...]:
        """The effect's extra states at rest under total load ``level`` (N*m reduced)."""
        return ()

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        raise NotImplementedError


# ---- backlash --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Backlash(_Base):
    """A gap in an element the mill file says is tight (seed Fig. 1a).

    Parameters
    ----------
    location : str
        Element id.
    gap : float
        Total added gap ``a + b``, rad (reduced).
    gap_open : float
        Its open part on the drive side ``b``, rad (``0 <= gap_open <= gap``).
    """

    location: str
    gap: float = 2e-3
    gap_open: float = 0.0
    name: ClassVar[str] = "backlash"
    _params: ClassVar[tuple[str, ...]] = ("gap", "gap_open")

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        i = _element_index(ctx.mill, self.location, self.name)
        e = ctx.mill.elements[i]
        gap, gap_open = p[0], p[1]
        cn, cp = (ctx.contact_neg[i], ctx.contact_pos[i]) if ctx.contact_pos else (-e.a, e.b)
        a0, b0 = -cn, cp
        a1, b1 = a0 + gap - gap_open, b0 + gap_open
        d = ctx.delta[i]
        w = ctx.smoothing
        if w is None:
            new = laws.g1(d, a1, b1, e.k, e.k_gap, e.k, xp=ca)
            old = laws.g1(d, a0, b0, e.k, e.k_gap, e.k, xp=ca)
        else:
            new = laws.g1_smooth(d, a1, b1, e.k, e.k_gap, e.k, w, xp=ca)
            old = laws.g1_smooth(d, a0, b0, e.k, e.k_gap, e.k, w, xp=ca)
        return EffectTerms(element_torque={i: new - old})

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"gap": 0.0, "gap_open": 0.0}

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        return (ParamSpec("gap", 0.0, 0.03, 1e-3), ParamSpec("gap_open", 0.0, 0.03, 1e-3, False))


# ---- stiffness beyond a knee ---------------------------------------------------------------
@dataclass(frozen=True)
class _KneeStiffness(_Base):
    location: str
    knee: float = 3e-3
    k_ratio: float = 1.0
    _params: ClassVar[tuple[str, ...]] = ("knee", "k_ratio")

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        i = _element_index(ctx.mill, self.location, self.name)
        e = ctx.mill.elements[i]
        knee, k_ratio = p[0], p[1]
        cn, cp = (ctx.contact_neg[i], ctx.contact_pos[i]) if ctx.contact_pos else (-e.a, e.b)
        w = ctx.smoothing
        d = ctx.delta[i]
        d_pos = _smax(d - cp, w)
        d_neg = _smin(d - cn, w)
        extra = _smax(d_pos - knee, w) + _smin(d_neg + knee, w)
        return EffectTerms(element_torque={i: (k_ratio - 1.0) * e.k * extra})

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"knee": float(self.knee), "k_ratio": 1.0}

    #: Fractions of the largest static deflection the knee guesses sit at: roughly
    #: geometric over the whole range a knee can be seen in (beyond the largest
    #: deflection it is crossed in overshoots only), not fitted to any one case.
    KNEE_FRACTIONS: ClassVar[tuple[float, ...]] = (0.08, 0.15, 0.27, 0.45, 0.7, 1.0)

    def knee_guesses(self, mill: Mill, *, torque: float | None = None) -> tuple[float, ...]:
        """Knee positions worth trying first, rad.

        Parameters
        ----------
        mill : Mill
        torque : float, optional
            Largest static rolling torque in the data, N*m reduced (default the
            mill's nominal torque).

        Returns
        -------
        tuple of float
            :attr:`KNEE_FRACTIONS` of the element's static deflection under ``torque``.
        """
        d = typical_deflection(mill, self.location, torque=torque)
        return tuple(f * d for f in self.KNEE_FRACTIONS)


@dataclass(frozen=True)
class SofteningStiffness(_KneeStiffness):
    """Stiffness falls to ``k_ratio * k`` beyond ``knee`` rad past contact (seed Fig. 1b).

    Parameters
    ----------
    location : str
        Element id.
    knee : float
        Deflection beyond contact, on either side, where the stiffness changes, rad.
    k_ratio : float
        ``k_after / k``, in (0, 1).
    """

    k_ratio: float = 0.5
    name: ClassVar[str] = "softening_stiffness"

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        d = typical_deflection(mill, self.location)
        return (ParamSpec("knee", 0.02 * d, 3.0 * d, 0.3 * d),
                ParamSpec("k_ratio", 0.05, 1.0, 0.3))


@dataclass(frozen=True)
class HardeningStiffness(_KneeStiffness):
    """Stiffness rises to ``k_ratio * k`` beyond ``knee`` rad past contact (seed Fig. 1c).

    Parameters
    ----------
    location : str
        Element id.
    knee : float
        Deflection beyond contact where the stiffness changes, rad.
    k_ratio : float
        ``k_after / k``, above 1.
    """

    k_ratio: float = 2.0
    name: ClassVar[str] = "hardening_stiffness"

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        d = typical_deflection(mill, self.location)
        return (ParamSpec("knee", 0.02 * d, 3.0 * d, 0.3 * d),
                ParamSpec("k_ratio", 1.0, 8.0, 1.0))


# ---- spindle imbalance ---------------------------------------------------------------------
@dataclass(frozen=True)
class SpindleImbalance(_Base):
    """An under- or over-weighted spindle: its open gap swings twice per roll revolution.

    ``gap_open += amplitude * sin(2 * phi + phase)`` with the physical roll angle
    ``phi = (Omega * t + theta_to) / ratio`` (``Omega`` the nominal motor speed,
    ``theta_to`` the roll-side mass's angle relative to nominal rotation, ``ratio``
    the spindle's).  The total gap stays; the swing only matters while the
    spindle is near or inside its gap, so it is weak under load (effects.md).

    Parameters
    ----------
    location : str
        The spindle's element id.
    amplitude : float
        Swing of the open part of the gap, rad (reduced).
    phase : float
        Phase at ``t = 0`` and zero angle, rad.
    """

    location: str
    amplitude: float = 5e-4
    phase: float = 0.0
    name: ClassVar[str] = "spindle_imbalance"
    _params: ClassVar[tuple[str, ...]] = ("amplitude", "phase")
    #: The idle state before a bite depends on the roll angle's history (a model of
    #: windows should run through the idle time rather than start at rest).
    needs_history: ClassVar[bool] = True

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        i = _element_index(ctx.mill, self.location, self.name)
        e = ctx.mill.elements[i]
        j = ctx.mill.mass_index(e.to)
        phi = (ctx.motor_speed * ctx.t + ctx.theta[j]) / e.ratio
        return EffectTerms(gap_open_shift={i: p[0] * ca.sin(2.0 * phi + p[1])})

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"amplitude": 0.0, "phase": float(self.phase)}

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        return (ParamSpec("amplitude", 0.0, 0.02, 5e-4),
                ParamSpec("phase", -4 * math.pi, 4 * math.pi, 1.0))

    def open_shift(self, mill: Mill, amplitude: float, phase: float, t: float,
                   theta_to: float = 0.0) -> float:
        """The shift of the open part of the gap at time ``t``, rad (as :meth:`terms`).

        Parameters
        ----------
        mill : Mill
        amplitude, phase : float
            The effect's parameters (rad).
        t : float
            Time, s from the recording's start.
        theta_to : float
            Angle of the roll-side mass relative to nominal rotation, rad (reduced).
        """
        e = mill.element(self.location)
        phi = (mill.motor_speed * t + theta_to) / e.ratio
        return float(amplitude * math.sin(2.0 * phi + phase))

    def roll_speed_hz(self, mill: Mill) -> float:
        """Physical roll speed of the spindle's shaft, revolutions per second."""
        return mill.motor_speed / (2 * math.pi) / mill.element(self.location).ratio


# ---- coulomb friction ----------------------------------------------------------------------
@dataclass(frozen=True)
class CoulombFriction(_Base):
    """Dry friction across an element: ``force * tanh(d(delta)/dt / v_smooth)``.

    Acts on the element's relative speed at all times (gap open or not) and adds
    to the torque the element transmits, so its torque channel reads it.

    Parameters
    ----------
    location : str
        Element id.
    force : float
        Friction torque, N*m (reduced).
    v_smooth : float
        Relative speed over which the sign is smoothed, rad/s (reduced).
    """

    location: str
    force: float = 3e3
    v_smooth: float = 5e-3
    name: ClassVar[str] = "coulomb_friction"
    _params: ClassVar[tuple[str, ...]] = ("force", "v_smooth")

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        i = _element_index(ctx.mill, self.location, self.name)
        return EffectTerms(element_torque={i: p[0] * ca.tanh(ctx.ddelta[i] / p[1])})

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"force": 0.0, "v_smooth": float(self.v_smooth)}

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        from .scenario import nominal_torque

        t = nominal_torque(mill)
        return (ParamSpec("force", 0.0, 0.3 * t, 0.01 * t),
                ParamSpec("v_smooth", 1e-4, 0.1, 5e-3, False))


# ---- drag (a nuisance of every fit, not a named effect) ---------------------------------
@dataclass(frozen=True)
class Drag(_Base):
    """A constant drag torque on one mass: bearing, gear-mesh and windage losses.

    The mass turns at the nominal speed in one direction, so its losses oppose
    rotation with a constant torque (a load on that mass, not on the rolls).
    Between bars such drag holds the elements between the motor and the mass
    against their drive flanks, and their torque channels read more than the
    channels nearer the rolls.  Not an effects.md name: the fit carries it as a
    nuisance (:func:`ident.fit.model.drag_masses`), the discrepancy workflow
    never names it.

    Parameters
    ----------
    location : str
        Mass id.
    torque : float
        Drag torque, N*m (reduced), positive against rotation.
    """

    location: str
    torque: float = 0.0
    name: ClassVar[str] = "drag"
    _params: ClassVar[tuple[str, ...]] = ("torque",)

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        try:
            i = ctx.mill.mass_index(self.location)
        except Exception:  # noqa: BLE001 - name the mass and the choices
            raise IdentError(f"drag: location must be a mass of mill '{ctx.mill.name}'. "
                             f"Got {self.location!r}.") from None
        e = np.zeros(len(ctx.mill.masses))
        e[i] = 1.0
        return EffectTerms(mass_torque=-ca.DM(e) * p[0])

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"torque": 0.0}

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        from .scenario import nominal_torque

        t = nominal_torque(mill)
        return (ParamSpec("torque", 0.0, 0.1 * t, 0.01 * t),)


# ---- strip coupling ------------------------------------------------------------------------
def _pair(mill: Mill, location: str, effect: str) -> tuple[int, int]:
    parts = location.split("-")
    if len(parts) != 2 or any(q not in mill.mass_ids for q in parts) or parts[0] == parts[1]:
        raise IdentError(f"{effect}: location must name two different masses of mill "
                         f"'{mill.name}' as 'Q6-Q7'. Got {location!r}.")
    return mill.mass_index(parts[0]), mill.mass_index(parts[1])


@dataclass(frozen=True)
class StripCoupling(_Base):
    """The strip ties two roll masses together: an element ``k, c`` between them.

    The element's deflection is ``theta_first - theta_second`` of ``location``
    (``"Q6-Q7"``), counted from the angles at ``t = 0``'s rest (zero at
    ``x_idle``).

    Parameters
    ----------
    location : str
        ``"Q6-Q7"``: the two masses.
    k : float
        Stiffness, N*m/rad (reduced).
    c : float
        Viscous damping, N*m*s/rad (reduced).
    """

    location: str = "Q6-Q7"
    k: float = 5e6
    c: float = 1e3
    name: ClassVar[str] = "strip_coupling"
    _params: ClassVar[tuple[str, ...]] = ("k", "c")

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        i, j = _pair(ctx.mill, self.location, self.name)
        k, c = p[0], p[1]
        return EffectTerms(extra_elements=((i, j, lambda d, dd: k * d + c * dd),))

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"k": 0.0, "c": 0.0}

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        kref = float(np.median([e.k for e in mill.elements]))
        return (ParamSpec("k", 0.0, 5.0 * kref, 0.1 * kref),
                ParamSpec("c", 0.0, 5e-3 * kref, 2.5e-5 * kref))


# ---- torque-loop lag -----------------------------------------------------------------------
@dataclass(frozen=True)
class TorqueLoopLag(_Base):
    """The drive's torque loop lags: ``T_motor' = (T_command - T_motor) / tau``.

    Adds one state, ``lag:T_motor`` (N*m), the torque the motor actually gives.

    Parameters
    ----------
    location : str
        The motor mass.
    tau : float
        Time constant, s.
    """

    location: str
    tau: float = 0.01
    name: ClassVar[str] = "torque_loop_lag"
    _params: ClassVar[tuple[str, ...]] = ("tau",)

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        if self.location != ctx.mill.motor.mass:
            raise IdentError(f"{self.name}: location must be the motor mass "
                             f"{ctx.mill.motor.mass!r}. Got {self.location!r}.")
        s = ca.SX.sym(f"lag_{self.location}")
        return EffectTerms(motor_torque=s, states=s,
                           state_derivatives=(ctx.T_motor_command - s) / p[0],
                           state_names=(f"{self.key}:T_motor",), state_initial=(0.0,))

    def neutral(self, mill: Mill) -> dict[str, float]:
        return {"tau": float(self.tau)}

    def static_states(self, mill: Mill, level: float) -> tuple[float, ...]:
        return (float(level),)

    def specs(self, mill: Mill) -> tuple[ParamSpec, ...]:
        return (ParamSpec("tau", 1e-3, 0.2, 0.01),)


# ---- a gate over any effect -----------------------------------------------------------------
@dataclass(frozen=True)
class Gated:
    """An effect multiplied by a ``gate`` parameter (0 off, 1 the effect itself).

    Every addition (element and mass torques, gap shifts, extra elements) is
    scaled by ``gate``; a replaced motor torque is blended with the command.
    The effect's own states keep running, so a gated-off model has the same
    state layout.  ``name`` and ``location`` are the inner effect's; the
    parameters are the inner ones plus ``gate``.
    """

    effect: Any
    gate: float = 1.0

    @property
    def name(self) -> str:
        return self.effect.name

    @property
    def location(self) -> str:
        return self.effect.location

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.effect.param_names) + ("gate",)

    @property
    def param_defaults(self) -> tuple[float, ...]:
        return tuple(self.effect.param_defaults) + (float(self.gate),)

    def terms(self, ctx: Any, p: Any) -> EffectTerms:
        n = len(self.effect.param_names)
        g = p[n]
        inner = self.effect.terms(ctx, p[:n])
        motor = None
        if inner.motor_torque is not None:
            motor = ctx.T_motor_command + g * (inner.motor_torque - ctx.T_motor_command)
        extra = tuple((i, j, (lambda fn: (lambda d, dd: g * fn(d, dd)))(fn))
                      for i, j, fn in inner.extra_elements)
        return EffectTerms(
            element_torque={i: g * v for i, v in inner.element_torque.items()},
            mass_torque=None if inner.mass_torque is None else g * inner.mass_torque,
            gap_open_shift={i: g * v for i, v in inner.gap_open_shift.items()},
            motor_torque=motor, states=inner.states, state_derivatives=inner.state_derivatives,
            state_names=inner.state_names, state_initial=inner.state_initial,
            extra_elements=extra)

    def static_states(self, mill: Mill, level: float) -> tuple[float, ...]:
        return self.effect.static_states(mill, level)


# ---- a sensor-chain filter (outside the library) ------------------------------------------
@dataclass(frozen=True)
class SensorFilter:
    """A causal Butterworth low-pass in a channel's sensor chain (not a model term).

    Outside effects.md on purpose: the model cannot express it, so the
    discrepancy workflow should answer ``explained: false`` for it.

    Parameters
    ----------
    channel : str
        Element id (or channel name) whose recorded torque passes the filter.
    cutoff_hz : float
        -3 dB frequency, Hz.
    order : int
        Butterworth order.
    """

    channel: str
    cutoff_hz: float = 25.0
    order: int = 2
    name: ClassVar[str] = "sensor_filter"

    def apply(self, x: np.ndarray, rate_hz: float) -> np.ndarray:
        """Filter samples ``x`` (any unit) taken at ``rate_hz``; starts at rest on ``x[0]``."""
        from scipy import signal

        if not 0 < self.cutoff_hz < rate_hz / 2:
            raise IdentError(f"SensorFilter cutoff_hz must lie in (0, {rate_hz / 2}) Hz. "
                             f"Got {self.cutoff_hz}.")
        sos = signal.butter(self.order, self.cutoff_hz, fs=rate_hz, output="sos")
        zi = signal.sosfilt_zi(sos) * x[0]
        y, _ = signal.sosfilt(sos, x, zi=zi)
        return y


EFFECT_CLASSES: dict[str, type] = {
    "backlash": Backlash,
    "softening_stiffness": SofteningStiffness,
    "hardening_stiffness": HardeningStiffness,
    "spindle_imbalance": SpindleImbalance,
    "coulomb_friction": CoulombFriction,
    "strip_coupling": StripCoupling,
    "torque_loop_lag": TorqueLoopLag,
}


def make_effect(name: str, location: str, **params: float) -> Any:
    """The effect called ``name`` (effects.md) at ``location`` with parameter values.

    Raises
    ------
    IdentError
        Unknown effect name or parameter.
    """
    cls = EFFECT_CLASSES.get(name)
    if cls is None:
        raise IdentError(f"unknown effect {name!r}; expected one of {', '.join(EFFECT_NAMES)}.")
    unknown = set(params) - set(cls._params)
    if unknown:
        raise IdentError(f"effect {name!r} has no parameter {sorted(unknown)}; expected "
                         f"{list(cls._params)}.")
    return cls(location, **params)


def spindles(mill: Mill) -> tuple[str, ...]:
    """Elements touching a load mass (the spindles of seed Fig. 2), mill-file order."""
    load = set(mill.load.masses)
    return tuple(e.id for e in mill.elements if e.to in load or e.from_ in load)


def roll_pairs(mill: Mill) -> tuple[str, ...]:
    """Pairs of load masses as ``"Q6-Q7"`` (strip coupling locations)."""
    ms = mill.load.masses
    return tuple(f"{ms[i]}-{ms[j]}" for i in range(len(ms)) for j in range(i + 1, len(ms)))


def candidate_locations(mill: Mill, name: str) -> tuple[str, ...]:
    """Where effect ``name`` can sit in ``mill`` (see the module docstring)."""
    if name == "backlash":
        return tuple(e.id for e in mill.elements if e.gap == 0.0)
    if name in ("softening_stiffness", "hardening_stiffness", "coulomb_friction"):
        return mill.element_ids
    if name == "spindle_imbalance":
        return spindles(mill)
    if name == "strip_coupling":
        return roll_pairs(mill)
    if name == "torque_loop_lag":
        return (mill.motor.mass,)
    raise IdentError(f"unknown effect {name!r}; expected one of {', '.join(EFFECT_NAMES)}.")
