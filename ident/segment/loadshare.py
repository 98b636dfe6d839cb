"""Where the rolling torque goes: static load fractions and distances to the rolls.

In steady rolling (constant speed) every mass is in equilibrium, so an element
carries the static part of the rolling torque that acts beyond it.  The
*load fraction* of an element is that static torque divided by the total rolling
torque, both reduced to the motor shaft:

* in a tree (the usual driveline), the sum of the ``[load]`` shares of the masses on
  the element's ``to`` side (the side away from the motor), with a minus sign if the
  motor is on its ``to`` side (the element points towards the motor);
* with closed loops (rolls meeting through the strip) the split depends on the
  stiffnesses: the motor is held, the loads applied (``K theta = tau``, the motor's
  row removed) and each element's torque ``k (theta_from - theta_to)`` read off.

Both give the same answer on a tree.  Sign conventions as in
:mod:`ident.description`: positive torque drives the rolls.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..description import Mill
from ..errors import MillFileError

__all__ = ["load_fractions", "distance_to_load"]


def _adjacency(mill: Mill) -> dict[str, list[tuple[str, str]]]:
    adj: dict[str, list[tuple[str, str]]] = {m.id: [] for m in mill.masses}
    for e in mill.elements:
        adj[e.from_].append((e.to, e.id))
        adj[e.to].append((e.from_, e.id))
    return adj


def _is_tree(mill: Mill) -> bool:
    pairs = {frozenset((e.from_, e.to)) for e in mill.elements}
    return len(mill.elements) == len(mill.masses) - 1 and len(pairs) == len(mill.elements)


def load_fractions(mill: Mill) -> dict[str, float]:
    """Static share of the total rolling torque each element carries.

    Parameters
    ----------
    mill : Mill

    Returns
    -------
    dict of str to float
        Element id -> fraction (dimensionless): the element's static torque, reduced
        to the motor shaft, per unit of total rolling torque.  Positive when the
        element transmits from ``from`` to ``to``.

    Raises
    ------
    MillFileError
        The stiffness problem of a looped driveline is singular.
    """
    share = dict(zip(mill.load.masses, mill.load.share))
    motor = mill.motor.mass
    if _is_tree(mill):
        adj = _adjacency(mill)
        out: dict[str, float] = {}
        for e in mill.elements:
            # the masses reachable from `to` without crossing e
            seen = {e.from_}
            stack = [e.to]
            side: set[str] = set()
            while stack:
                m = stack.pop()
                if m in seen:
                    continue
                seen.add(m)
                side.add(m)
                stack += [n for n, eid in adj[m] if eid != e.id]
            if motor in side:  # the element points towards the motor
                out[e.id] = -sum(v for m, v in share.items() if m not in side)
            else:
                out[e.id] = sum(v for m, v in share.items() if m in side)
        return out
    ids = list(mill.mass_ids)
    idx = {m: i for i, m in enumerate(ids)}
    n = len(ids)
    K = np.zeros((n, n))
    for e in mill.elements:
        i, j = idx[e.from_], idx[e.to]
        K[i, i] += e.k
        K[j, j] += e.k
        K[i, j] -= e.k
        K[j, i] -= e.k
    tau = np.zeros(n)
    for m, v in share.items():
        tau[idx[m]] -= v  # the rolling load acts against rotation
    keep = [i for i in range(n) if ids[i] != motor]
    try:
        theta_r = np.linalg.solve(K[np.ix_(keep, keep)], tau[keep])
    except np.linalg.LinAlgError:
        raise MillFileError("the static stiffness problem is singular (is every mass "
                            "connected to the motor?)", path=mill.source) from None
    theta = np.zeros(n)
    theta[keep] = theta_r
    return {e.id: float(e.k * (theta[idx[e.from_]] - theta[idx[e.to]])) for e in mill.elements}


def distance_to_load(mill: Mill) -> dict[str, int]:
    """Graph distance (number of elements) from each element to the nearest load mass.

    An element touching a ``[load]`` mass has distance 0; the torque channel with the
    smallest distance is the one nearest the rolls, which sees a load step first.
    """
    adj = _adjacency(mill)
    dist = {m: -1 for m in adj}
    q: deque[str] = deque()
    for m in mill.load.masses:
        dist[m] = 0
        q.append(m)
    while q:
        m = q.popleft()
        for nb, _ in adj[m]:
            if dist[nb] < 0:
                dist[nb] = dist[m] + 1
                q.append(nb)
    return {e.id: min(d for d in (dist[e.from_], dist[e.to]) if d >= 0) for e in mill.elements}
