"""Linear baseline of the driveline: matrices, natural frequencies and mode shapes.

The baseline is the driveline with every gap closed (contact stiffness ``k``
on both sides), no knee, and the motor's speed loop open: a free-free chain
whose rigid-body mode is left out (cli.md, ``ident frequencies``).  The seed
compares the measured response with exactly this reference (section 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ..description import Mill

__all__ = ["incidence", "angles_from_deflections", "mass_matrix", "stiffness_matrix",
           "damping_matrix", "LinearModes", "natural_modes"]


def incidence(mill: Mill) -> np.ndarray:
    """Element-by-mass incidence matrix ``D`` with ``delta = D @ theta``.

    Row ``e`` holds +1 at the element's ``from`` mass and -1 at its ``to`` mass,
    so ``delta_e = theta_from - theta_to``; the torques on the masses are
    ``-D.T @ tau`` for element torques ``tau``.

    Returns
    -------
    ndarray, shape (n_elements, n_masses)
    """
    D = np.zeros((len(mill.elements), len(mill.masses)))
    for i, e in enumerate(mill.elements):
        D[i, mill.mass_index(e.from_)] = 1.0
        D[i, mill.mass_index(e.to)] = -1.0
    return D


def angles_from_deflections(mill: Mill, delta: np.ndarray, im: int) -> np.ndarray:
    """Angles with ``theta[im] = 0`` and ``D @ theta = delta`` along a spanning tree.

    Parameters
    ----------
    mill : Mill
    delta : ndarray
        One deflection per element (rad), in the mill's element order.
    im : int
        Index of the mass whose angle is the reference (zero), usually the motor.

    Returns
    -------
    ndarray
        One angle per mass; on a closed loop the deflections of the elements
        outside the spanning tree are implied, not imposed.
    """
    n = len(mill.masses)
    theta = np.full(n, np.nan)
    theta[im] = 0.0
    changed = True
    while changed:
        changed = False
        for j, e in enumerate(mill.elements):
            a, b = mill.mass_index(e.from_), mill.mass_index(e.to)
            if np.isnan(theta[b]) and not np.isnan(theta[a]):
                theta[b] = theta[a] - delta[j]
                changed = True
            elif np.isnan(theta[a]) and not np.isnan(theta[b]):
                theta[a] = theta[b] + delta[j]
                changed = True
    return np.nan_to_num(theta)


def mass_matrix(mill: Mill) -> np.ndarray:
    """Diagonal inertia matrix, kg*m^2 (reduced), shape (n_masses, n_masses)."""
    return np.diag([m.J for m in mill.masses])


def stiffness_matrix(mill: Mill) -> np.ndarray:
    """Stiffness matrix with gaps closed, N*m/rad, shape (n_masses, n_masses)."""
    D = incidence(mill)
    return D.T @ np.diag([e.k for e in mill.elements]) @ D


def damping_matrix(mill: Mill) -> np.ndarray:
    """Viscous damping matrix of the elements, N*m*s/rad (speed loop excluded)."""
    D = incidence(mill)
    return D.T @ np.diag([e.c for e in mill.elements]) @ D


@dataclass(frozen=True)
class LinearModes:
    """Natural frequencies and mass-normalised mode shapes of the baseline.

    Attributes
    ----------
    frequencies_hz : ndarray, shape (n_modes,)
        Undamped natural frequencies, Hz, ascending, rigid-body mode left out.
    shapes : ndarray, shape (n_masses, n_modes)
        Mode shapes (angles), each scaled to unit largest absolute entry with that
        entry positive.
    damping_ratios : ndarray, shape (n_modes,)
        Modal damping ratios from the element dampers (proportional approximation).
    mass_ids : tuple of str
        Row labels of ``shapes``.
    """

    frequencies_hz: np.ndarray
    shapes: np.ndarray
    damping_ratios: np.ndarray
    mass_ids: tuple[str, ...]

    def element_shapes(self, mill: Mill) -> np.ndarray:
        """Modal deflections ``delta`` per element, shape (n_elements, n_modes)."""
        return incidence(mill) @ self.shapes


def natural_modes(mill: Mill) -> LinearModes:
    """Natural frequencies and mode shapes of the linear baseline (gaps closed).

    Solves ``K v = w**2 M v`` and drops the rigid-body mode(s) (``w`` near 0).

    Parameters
    ----------
    mill : Mill

    Returns
    -------
    LinearModes
    """
    M = mass_matrix(mill)
    K = stiffness_matrix(mill)
    C = damping_matrix(mill)
    w2, V = scipy.linalg.eigh(K, M)
    scale = max(float(np.max(np.abs(w2))), 1.0)
    keep = w2 > 1e-9 * scale
    w = np.sqrt(w2[keep])
    V = V[:, keep]
    # modal damping ratios from the mass-normalised shapes (eigh normalises V.T M V = I)
    zeta = np.array([V[:, i] @ C @ V[:, i] / (2.0 * w[i]) for i in range(V.shape[1])])
    shapes = V / np.max(np.abs(V), axis=0)
    sign = np.sign(shapes[np.argmax(np.abs(shapes), axis=0), np.arange(shapes.shape[1])])
    shapes = shapes * sign
    return LinearModes(frequencies_hz=w / (2.0 * np.pi), shapes=shapes, damping_ratios=zeta,
                       mass_ids=mill.mass_ids)
