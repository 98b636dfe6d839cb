"""Stiffness characteristics of seed section 1.2 and Fig. 1, written once.

Every law takes an array namespace ``xp`` and works both numerically
(``xp=numpy``, the default) and symbolically (``xp=casadi``): the two share
``fmax``, ``fmin``, ``fabs``, ``sqrt``, ``arctan`` and ``tanh``.  The simulator,
the collocation fit and the tests all call these same functions.

Notation (seed Fig. 1a, mill-config.md): deflection ``delta`` (rad, reduced),
``a`` the closed part of the gap on the negative side, ``b`` the open part on
the drive side, ``k1``/``k3`` the stiffness beyond contact on the negative and
positive side, ``k2`` the stiffness inside the gap.

* :func:`g1` -- the logical (piecewise linear) law.
* :func:`g2` -- polynomial ``a1*d + a2*d**2 + a3*d**3``.
* :func:`g3` -- arc-tangent ``d*a0*arctan(sigma*|d|)``.
* :func:`g4` -- hyperbolic tangent ``d*a0*tanh(sigma*|d|)``.
* :func:`piecewise` -- g1 with softening or hardening beyond a knee (Fig. 1b, 1c).
* :func:`g1_smooth` / :func:`piecewise_smooth` -- the same with kinks rounded over
  a width ``w`` (rad) for the optimiser; ``|g1_smooth - g1| <= (k1 + k3 + 2*k2) * w / 2``
  everywhere (:func:`g1_smooth_error_bound`, from the ``w/2`` of :func:`smooth_max`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["g1", "g2", "g3", "g4", "piecewise", "smooth_max", "smooth_min", "smooth_max_c1",
           "smooth_min_c1", "g1_smooth",
           "piecewise_smooth", "g1_smooth_error_bound", "element_torque_law"]


def g1(delta: Any, a: Any, b: Any, k1: Any, k2: Any, k3: Any, xp: Any = np) -> Any:
    """Logical-type law g1 of seed section 1.2 (Fig. 1a).

    ``k3*(d - b) + k2*b`` for ``d > b``; ``k2*d`` for ``-a <= d <= b``;
    ``k1*(d + a) - k2*a`` for ``d < -a``.

    Parameters
    ----------
    delta : array_like or casadi expression
        Deflection, rad.
    a, b : float
        Gap on the negative and positive side, rad (``a, b >= 0``).
    k1, k2, k3 : float
        Stiffness below, inside and above the gap, N*m/rad.

    Returns
    -------
    Restoring torque, N*m, same shape as ``delta``.
    """
    inside = xp.fmin(xp.fmax(delta, -a), b)
    return k2 * inside + k3 * xp.fmax(delta - b, 0) + k1 * xp.fmin(delta + a, 0)


def g2(delta: Any, a1: Any, a2: Any, a3: Any, xp: Any = np) -> Any:
    """Polynomial law g2 = a1*d + a2*d**2 + a3*d**3 (seed section 1.2)."""
    return a1 * delta + a2 * delta ** 2 + a3 * delta ** 3


def g3(delta: Any, a0: Any, sigma: Any, xp: Any = np) -> Any:
    """Arc-tangent law g3 = d*a0*arctan(sigma*|d|) (seed section 1.2).

    Far from zero it tends to ``(pi/2)*a0*(d - sign(d)*2/(pi*sigma))``: stiffness
    ``pi*a0/2`` behind an apparent half-gap ``2/(pi*sigma)``.
    """
    return delta * a0 * xp.arctan(sigma * xp.fabs(delta))


def g4(delta: Any, a0: Any, sigma: Any, xp: Any = np) -> Any:
    """Hyperbolic-tangent law g4 = d*a0*tanh(sigma*|d|) (seed section 1.2)."""
    return delta * a0 * xp.tanh(sigma * xp.fabs(delta))


def _contact_torque(d_pos: Any, d_neg: Any, k1: Any, k3: Any, knee: Any, k_after: Any,
                    fmax: Any, fmin: Any) -> Any:
    """Torque of contact deflections ``d_pos >= 0`` and ``d_neg <= 0`` with a knee."""
    pos = k3 * d_pos + (k_after - k3) * fmax(d_pos - knee, 0)
    neg = k1 * d_neg + (k_after - k1) * fmin(d_neg + knee, 0)
    return pos + neg


def piecewise(delta: Any, a: Any, b: Any, k1: Any, k2: Any, k3: Any, knee: Any = None,
              k_after: Any = None, xp: Any = np) -> Any:
    """g1 with a stiffness change ``knee`` rad beyond contact on either side.

    Beyond the knee the stiffness is ``k_after``: below ``k`` for softening
    (seed Fig. 1b: housing or bolting gap opening), above for hardening (Fig. 1c).
    Without ``knee`` this is :func:`g1`.
    """
    if knee is None or k_after is None:
        return g1(delta, a, b, k1, k2, k3, xp)
    inside = xp.fmin(xp.fmax(delta, -a), b)
    d_pos = xp.fmax(delta - b, 0)
    d_neg = xp.fmin(delta + a, 0)
    return k2 * inside + _contact_torque(d_pos, d_neg, k1, k3, knee, k_after, xp.fmax, xp.fmin)


def smooth_max(x: Any, w: Any, xp: Any = np) -> Any:
    """Smooth ``max(x, 0)``: ``(x + sqrt(x**2 + w**2)) / 2``.

    ``0 <= smooth_max(x, w) - max(x, 0) <= w/2``, the bound reached at ``x = 0``
    and the error falling as ``w**2/(4|x|)`` away from it.
    """
    return 0.5 * (x + xp.sqrt(x * x + w * w))


def smooth_min(x: Any, w: Any, xp: Any = np) -> Any:
    """Smooth ``min(x, 0)``: ``-smooth_max(-x, w)``."""
    return 0.5 * (x - xp.sqrt(x * x + w * w))


def smooth_max_c1(x: Any, w: Any, xp: Any = np) -> Any:
    """Smooth ``max(x, 0)`` rounded only on ``|x| < w/2`` (quadratic blend, C1).

    Exact outside ``[-w/2, w/2]``, ``0 <= smooth_max_c1 - max(x, 0) <= w/8``:
    the smoothing leaves no tail, so a contact begins no earlier than ``w/2``
    before the kink.  For the same width it biases impact dynamics (and
    fitted gaps) about three times less than :func:`smooth_max`.
    """
    q = xp.fmin(xp.fmax(x + 0.5 * w, 0), w)
    return q * q / (2 * w) + xp.fmax(x - 0.5 * w, 0)


def smooth_min_c1(x: Any, w: Any, xp: Any = np) -> Any:
    """Smooth ``min(x, 0)``: ``-smooth_max_c1(-x, w)``."""
    return -smooth_max_c1(-x, w, xp)


def _smoothers(kind: str) -> tuple[Any, Any]:
    if kind == "sqrt":
        return smooth_max, smooth_min
    if kind == "c1":
        return smooth_max_c1, smooth_min_c1
    raise ValueError(f"smoothing kind must be 'sqrt' or 'c1'. Got {kind!r}.")


def g1_smooth(delta: Any, a: Any, b: Any, k1: Any, k2: Any, k3: Any, w: Any,
              xp: Any = np, kind: str = "sqrt") -> Any:
    """g1 with its kinks rounded over width ``w`` (rad): explicit gaps for the optimiser.

    ``|g1_smooth - g1| <= (k1 + k3 + 2*k2) * w / 2`` for every ``delta``
    (:func:`g1_smooth_error_bound`); as ``w -> 0`` it tends to :func:`g1`.
    """
    smax, smin = _smoothers(kind)
    d_pos = smax(delta - b, w, xp)
    d_neg = smin(delta + a, w, xp)
    inside = delta - d_pos - d_neg  # = clip(delta, -a, b) up to the rounding
    return k2 * inside + k3 * d_pos + k1 * d_neg


def piecewise_smooth(delta: Any, a: Any, b: Any, k1: Any, k2: Any, k3: Any, w: Any,
                     knee: Any = None, k_after: Any = None, xp: Any = np,
                     kind: str = "sqrt") -> Any:
    """:func:`piecewise` with every kink rounded over width ``w`` (rad).

    ``kind``: ``"sqrt"`` (:func:`smooth_max`) or ``"c1"`` (:func:`smooth_max_c1`).
    """
    if knee is None or k_after is None:
        return g1_smooth(delta, a, b, k1, k2, k3, w, xp, kind)
    smax, smin = _smoothers(kind)
    d_pos = smax(delta - b, w, xp)
    d_neg = smin(delta + a, w, xp)
    inside = delta - d_pos - d_neg
    pos = k3 * d_pos + (k_after - k3) * smax(d_pos - knee, w, xp)
    neg = k1 * d_neg + (k_after - k1) * smin(d_neg + knee, w, xp)
    return k2 * inside + pos + neg


def g1_smooth_error_bound(k1: float, k2: float, k3: float, w: float) -> float:
    """Upper bound of ``|g1_smooth - g1|`` over all deflections, N*m."""
    return (k1 + k3 + 2.0 * k2) * w / 2.0


def element_torque_law(element: Any, delta: Any, *, gap: Any = None, gap_open: Any = None,
                       smoothing: Any = None, xp: Any = np) -> Any:
    """Restoring torque g(delta) of a mill-file element (reduced, N*m).

    Uses the element's ``gap``, ``gap_open``, ``k``, ``k_gap`` and knee unless
    ``gap``/``gap_open`` are given (symbols in a fit).  With ``smoothing`` (rad)
    the kinks are rounded (:func:`piecewise_smooth`); without, exact.
    """
    g = element.gap if gap is None else gap
    b = element.gap_open if gap_open is None else gap_open
    a = g - b
    knee = element.knee if element.stiffness.value != "linear" else None
    k_after = element.k_after if knee is not None else None
    if smoothing is None:
        return piecewise(delta, a, b, element.k, element.k_gap, element.k, knee, k_after, xp)
    return piecewise_smooth(delta, a, b, element.k, element.k_gap, element.k, smoothing, knee,
                            k_after, xp)
