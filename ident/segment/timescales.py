"""The mill's own time scale for the segmenter: its lowest torsional mode.

The ring-down after a load step is dominated by the lowest natural mode of the
driveline (seed, section 2: the 12 Hz mode of the hot stand; 14.5 Hz on the cold
stand ``cold-s5``), so the segmenter smooths over that mode's period and waits a
period for a ring-down to decay.  The mode is the linear baseline's (every gap
closed, speed loop open, free-free, the rigid-body mode left out): the same
eigenproblem ``K v = w**2 M v`` as :func:`ident.model.linear.natural_modes`, solved
here because ``segment`` sits upstream of ``model`` and may not import it
(``tests/test_imports.py``); ``tests/test_segment.py`` checks that both agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ..description import Mill

__all__ = ["LowestMode", "lowest_mode"]


@dataclass(frozen=True)
class LowestMode:
    """The lowest elastic mode of the linear baseline.

    Attributes
    ----------
    freq_hz : float
        Undamped natural frequency, Hz.
    damping_ratio : float
        Modal damping ratio from the element dampers (dimensionless).
    """

    freq_hz: float
    damping_ratio: float

    @property
    def period_s(self) -> float:
        """One period, s."""
        return 1.0 / self.freq_hz


def lowest_mode(mill: Mill) -> LowestMode:
    """Lowest natural frequency and its damping ratio, from the mill description.

    Parameters
    ----------
    mill : Mill

    Returns
    -------
    LowestMode

    Raises
    ------
    ValueError
        The driveline has no elastic mode (a single mass).
    """
    idx = {m.id: i for i, m in enumerate(mill.masses)}
    n = len(mill.masses)
    D = np.zeros((len(mill.elements), n))
    for j, e in enumerate(mill.elements):
        D[j, idx[e.from_]] = 1.0
        D[j, idx[e.to]] = -1.0
    M = np.diag([m.J for m in mill.masses])
    K = D.T @ np.diag([e.k for e in mill.elements]) @ D
    C = D.T @ np.diag([e.c for e in mill.elements]) @ D
    w2, V = scipy.linalg.eigh(K, M)
    scale = max(float(np.max(np.abs(w2))), 1.0)
    elastic = np.flatnonzero(w2 > 1e-9 * scale)
    if elastic.size == 0:
        raise ValueError(f"mill {mill.name!r} has no elastic torsional mode")
    i = int(elastic[0])
    w = math.sqrt(float(w2[i]))
    v = V[:, i]
    return LowestMode(freq_hz=w / (2.0 * math.pi), damping_ratio=float(v @ C @ v / (2.0 * w)))
