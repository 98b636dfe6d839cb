"""Wear states by the maintenance limits of the mill file (cli.md, ``diagnose``)."""

from __future__ import annotations

import enum

from ..description import Bearing, Element

__all__ = ["WearState", "STATES", "element_state", "bearing_state"]


class WearState(str, enum.Enum):
    """An element's or bearing's condition."""

    GOOD = "good"
    WORN = "worn"
    CRITICAL = "critical"


#: the states in order of wear (class labels 0, 1, 2)
STATES: tuple[str, ...] = tuple(s.value for s in WearState)


def element_state(element: Element, gap_rad: float) -> WearState:
    """``worn`` above the element's ``gap_worn``, ``critical`` above ``gap_critical`` (rad)."""
    if gap_rad > element.gap_critical:
        return WearState.CRITICAL
    if gap_rad > element.gap_worn:
        return WearState.WORN
    return WearState.GOOD


def bearing_state(bearing: Bearing, clearance_m: float) -> WearState:
    """``worn`` above ``clearance_worn``, ``critical`` above ``clearance_critical`` (m)."""
    if clearance_m > bearing.clearance_critical:
        return WearState.CRITICAL
    if clearance_m > bearing.clearance_worn:
        return WearState.WORN
    return WearState.GOOD
