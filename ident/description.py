"""The one immutable description of a mill's driveline, and its sign conventions.

A mill file (see ``ident.io.millfile``) becomes a :class:`Mill`: a tree of frozen
dataclasses.  Variants are made with :meth:`Mill.with_overrides` or
``dataclasses.replace``; derived quantities (matrices, frequencies, the CasADi
right-hand side) are functions of the description in ``ident.model``.

Sign conventions (written once, tested in ``tests/test_conventions.py``)
-----------------------------------------------------------------------
* All mechanical parameters are **reduced to the motor shaft**: inertias in
  kg*m^2, stiffness in N*m/rad, damping in N*m*s/rad, angles in rad.  An
  element's ``ratio`` converts back: physical torque = reduced torque * ratio,
  physical speed = motor speed / ratio.
* Angles are measured in the direction of rotation while rolling; positive
  torque drives the rolls.  The rolling load acts against rotation.
* An element's deflection is ``delta = theta_from - theta_to`` (reduced).  It
  transmits ``g(delta) + c * d(delta)/dt`` from ``from`` to ``to``: the
  ``from`` mass feels minus that torque, the ``to`` mass plus.  A torque
  channel on the element reads that torque times ``ratio``.
* The gap follows seed Fig. 1a: ``a = gap - gap_open`` on the negative side,
  ``b = gap_open`` on the drive (positive) side, ``k1 = k3 = k`` and
  ``k2 = k_gap`` (0 unless given).  Driving torque closes the ``b`` side.
* Bearings: the whole mesh force of ``mesh`` loads the bearing along the line
  of action at ``pressure_angle_deg`` from the vertical, pointing up for
  positive mesh torque; gravity pulls the shaft down.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

__all__ = [
    "StiffnessKind",
    "Quantity",
    "Mass",
    "Element",
    "Load",
    "Motor",
    "Bearing",
    "Channel",
    "Mill",
]


class StiffnessKind(str, enum.Enum):
    """Shape of an element's stiffness beyond contact (seed Fig. 1)."""

    LINEAR = "linear"
    SOFTENING = "softening"
    HARDENING = "hardening"


class Quantity(str, enum.Enum):
    """What a channel measures."""

    TORQUE = "torque"
    ACCELERATION = "acceleration"
    SPEED = "speed"


@dataclass(frozen=True)
class Mass:
    """A rotating body.

    Attributes
    ----------
    id : str
    label : str
    J : float
        Moment of inertia reduced to the motor shaft, kg*m^2.
    """

    id: str
    J: float
    label: str = ""


@dataclass(frozen=True)
class Element:
    """An elastic link between two masses (coupling, shaft, mesh, spindle).

    Attributes
    ----------
    k, c : float
        Reduced stiffness (N*m/rad) and viscous damping (N*m*s/rad).
    ratio : float
        Speed ratio motor / this shaft; physical torque = reduced torque * ratio.
    gap, gap_open : float
        Total angular gap ``a + b`` and its open part ``b`` (drive side), rad, reduced.
    k_gap : float
        Stiffness inside the gap (seed k2), N*m/rad; 0 for a true dead zone.
    stiffness, knee, k_after :
        Softening or hardening beyond ``knee`` rad past contact (seed Fig. 1b, 1c).
    radius : float or None
        Tooth pitch radius, m, to report gaps in mm.
    gap_worn, gap_critical : float
        Maintenance limits, rad (reduced).
    """

    id: str
    from_: str
    to: str
    k: float
    c: float = 0.0
    ratio: float = 1.0
    gap: float = 0.0
    gap_open: float = 0.0
    k_gap: float = 0.0
    stiffness: StiffnessKind = StiffnessKind.LINEAR
    knee: float | None = None
    k_after: float | None = None
    radius: float | None = None
    gap_worn: float = 0.004
    gap_critical: float = 0.008
    label: str = ""

    @property
    def a(self) -> float:
        """Closed part of the gap on the negative side, rad (seed ``a``)."""
        return self.gap - self.gap_open

    @property
    def b(self) -> float:
        """Open part of the gap on the drive side, rad (seed ``b``)."""
        return self.gap_open

    def gap_mm(self, gap_rad: float | None = None) -> float | None:
        """Gap as a tooth-flank clearance in mm, or None without a radius.

        ``gap_mm = gap_rad / ratio * radius * 1000`` (mill-config.md).
        """
        if self.radius is None:
            return None
        g = self.gap if gap_rad is None else gap_rad
        return g / self.ratio * self.radius * 1000.0


@dataclass(frozen=True)
class Load:
    """Where the rolling torque acts: masses and their shares (sum 1)."""

    masses: tuple[str, ...]
    share: tuple[float, ...]


@dataclass(frozen=True)
class Motor:
    """The drive motor and its PI speed loop (ideal torque loop).

    Attributes
    ----------
    mass : str
        The motor rotor's mass id.
    kp : float
        Proportional gain, N*m per rad/s.
    ki : float
        Integral gain, N*m per rad.
    torque_limit : float or None
        Motor torque limit, N*m (reduced = motor shaft).
    """

    mass: str
    kp: float
    ki: float
    control: str = "pi_speed"
    torque_limit: float | None = None


@dataclass(frozen=True)
class Bearing:
    """A shaft in its bearing and housing: the radial model of seed Fig. 8a."""

    id: str
    mesh: str
    base_radius: float
    shaft_mass: float
    k_bearing: float
    clearance: float
    housing_mass: float
    k_housing: float
    ratio: float = 1.0
    pressure_angle_deg: float = 20.0
    c_bearing: float = 0.0
    k_housing_open: float | None = None
    housing_preload: float = math.inf
    c_housing: float = 0.0
    clearance_worn: float = 1.0e-3
    clearance_critical: float = 1.8e-3


@dataclass(frozen=True)
class Channel:
    """One recorded channel and how to read it.

    ``value_in_unit = scale * recorded + offset``; ``unit`` is converted to SI by
    ``ident.units``.  Exactly one of ``element`` (torque), ``bearing``
    (acceleration) and ``mass`` (speed) is set.
    """

    name: str
    quantity: Quantity
    unit: str
    element: str | None = None
    bearing: str | None = None
    mass: str | None = None
    direction: str | None = None
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class Mill:
    """One stand's driveline as its mill file describes it.

    Build it with :func:`ident.io.load_mill`; do not mutate it.
    """

    name: str
    masses: tuple[Mass, ...]
    elements: tuple[Element, ...]
    load: Load
    motor: Motor
    motor_speed_rpm: float
    bearings: tuple[Bearing, ...] = ()
    channels: tuple[Channel, ...] = ()
    description: str = ""
    source: str | None = field(default=None, compare=False)
    sha256: str = field(default="", compare=False)

    # ---- look-ups -----------------------------------------------------------------
    @property
    def mass_ids(self) -> tuple[str, ...]:
        return tuple(m.id for m in self.masses)

    @property
    def element_ids(self) -> tuple[str, ...]:
        return tuple(e.id for e in self.elements)

    def mass_index(self, mass_id: str) -> int:
        """Index of a mass in :attr:`masses` (the state ordering)."""
        for i, m in enumerate(self.masses):
            if m.id == mass_id:
                return i
        raise KeyError(mass_id)

    def element(self, element_id: str) -> Element:
        for e in self.elements:
            if e.id == element_id:
                return e
        raise KeyError(element_id)

    def bearing(self, bearing_id: str) -> Bearing:
        for b in self.bearings:
            if b.id == bearing_id:
                return b
        raise KeyError(bearing_id)

    def channel(self, name: str) -> Channel:
        for c in self.channels:
            if c.name == name:
                return c
        raise KeyError(name)

    @property
    def motor_speed(self) -> float:
        """Nominal motor speed, rad/s."""
        return self.motor_speed_rpm * 2.0 * math.pi / 60.0

    def torque_channels(self) -> tuple[Channel, ...]:
        return tuple(c for c in self.channels if c.quantity is Quantity.TORQUE)

    def acceleration_channels(self) -> tuple[Channel, ...]:
        return tuple(c for c in self.channels if c.quantity is Quantity.ACCELERATION)

    # ---- variants -----------------------------------------------------------------
    def with_overrides(self, overrides: Mapping[str, Any]) -> "Mill":
        """Return a copy with ``{"ID.KEY": value}`` overrides applied and validated.

        ``ID`` is a mass, element, bearing or channel id (or ``motor``,
        ``operation``); ``KEY`` is the mill-file key (``from``/``to`` for
        elements).  Used by the CLI's ``--set``.

        Raises
        ------
        ident.errors.MillFileError
            Unknown id or key, or a value the mill file would refuse.
        """
        from .schema import apply_overrides  # schema builds on this module

        return apply_overrides(self, overrides)

    def content_hash(self) -> str:
        """SHA-256 of the description's values (stable across file formatting)."""
        h = hashlib.sha256(repr(dataclasses.replace(self, source=None, sha256="")).encode())
        return h.hexdigest()
