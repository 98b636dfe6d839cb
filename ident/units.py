"""Unit conversion at the edges of ident.

Everything inside ident is SI: N*m, rad, rad/s, m/s^2, m, s.  Recordings and
reports may use other units; they are converted here and nowhere else.
"""

from __future__ import annotations

import math

__all__ = ["QUANTITY_UNITS", "G0", "to_si_factor", "rpm_to_rad_s", "rad_s_to_rpm", "normalize_unit",
           "quantity_of_unit"]

G0 = 9.80665  # m/s^2, standard gravity

#: Allowed units per channel quantity and their factor to SI.
QUANTITY_UNITS: dict[str, dict[str, float]] = {
    "torque": {"N*m": 1.0, "kN*m": 1.0e3, "MN*m": 1.0e6},
    "acceleration": {"m/s^2": 1.0, "g": G0},
    "speed": {"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0},
}

_ALIASES = {
    "nm": "N*m", "n*m": "N*m", "n·m": "N*m", "n.m": "N*m",
    "knm": "kN*m", "kn*m": "kN*m", "kn·m": "kN*m", "kn.m": "kN*m",
    "mnm": "MN*m", "mn*m": "MN*m", "mn·m": "MN*m", "mn.m": "MN*m",
    "m/s^2": "m/s^2", "m/s2": "m/s^2", "m/s**2": "m/s^2", "m/s²": "m/s^2",
    "g": "g", "rad/s": "rad/s", "rpm": "rpm", "1/min": "rpm", "raw": "raw",
}


def normalize_unit(unit: str) -> str:
    """Return the canonical spelling of ``unit`` (``'kNm'`` -> ``'kN*m'``).

    Unknown spellings are returned stripped but otherwise unchanged, so that
    the caller can report them.
    """
    u = unit.strip()
    return _ALIASES.get(u.lower().replace(" ", ""), u)


def to_si_factor(quantity: str, unit: str) -> float:
    """Factor that converts a value of ``quantity`` in ``unit`` to SI.

    Raises
    ------
    KeyError
        If the quantity or unit is unknown (callers turn it into a typed error).
    """
    return QUANTITY_UNITS[quantity][normalize_unit(unit)]


def rpm_to_rad_s(speed_rpm: float) -> float:
    """Convert a rotational speed from rpm to rad/s."""
    return speed_rpm * 2.0 * math.pi / 60.0


def rad_s_to_rpm(speed_rad_s: float) -> float:
    """Convert a rotational speed from rad/s to rpm."""
    return speed_rad_s * 60.0 / (2.0 * math.pi)


def quantity_of_unit(unit: str) -> str | None:
    """The quantity (``torque``, ``acceleration``, ``speed``) a unit belongs to, or None.

    Used to bring a recording to SI when no mill file maps its channels.
    """
    u = normalize_unit(unit)
    for quantity, units in QUANTITY_UNITS.items():
        if u in units:
            return quantity
    return None
