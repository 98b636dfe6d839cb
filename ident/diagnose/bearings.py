"""Bearing wear from the radial model: shaft trajectory and radial load vs clearance.

Seed section 2.2, Fig. 8: during a transient the shaft centre moves inside
its clearance (Fig. 8b, "the initial position of shaft was in the bottom");
the largest radial load on the bearing grows with the clearance (Fig. 8c),
and "a certain limit of load (about 1000 kN) will be overrun at the 1.8 mm
wear of bearing", which gives the maintenance point.  Here:

* :func:`shaft_trajectory` -- the shaft centre relative to the housing
  through one bite and release;
* :func:`radial_load_curve` -- the largest contact force over that transient
  for a range of clearances (one torsional simulation, one radial run per
  clearance: ``ident.diagnose.radial``);
* :func:`maintenance_clearance` -- where the curve crosses a load limit.

For the shipped ``hsm-f1`` stand at its nominal torque see
``tests/test_diagnose_bearings.py`` (the numbers are written there and in the
notebook ``notebooks/02_features.ipynb``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd

from ..description import Mill
from ..model.dynamics import ModelOptions
from ..model.scenario import Bar, Scenario, nominal_torque
from ..model.simulate import simulate
from .radial import simulate_radial

__all__ = ["RadialLoadCurve", "radial_load_curve", "maintenance_clearance", "shaft_trajectory"]


@dataclass(frozen=True)
class RadialLoadCurve:
    """Largest radial bearing load over a bite-and-release transient vs clearance.

    Attributes
    ----------
    bearing_id : str
    clearances_m : ndarray
        Radial clearances, m.
    max_load_n : ndarray
        Largest contact force over the transient at each clearance, N.
    static_load_n : float
        Mesh force at the static torque (quasi-static radial load), N.
    static_torque : float
        Total rolling torque of the transient, N*m reduced.
    """

    bearing_id: str
    clearances_m: np.ndarray
    max_load_n: np.ndarray
    static_load_n: float
    static_torque: float

    @property
    def dynamic_factor(self) -> np.ndarray:
        """``max_load_n`` over the static load."""
        return self.max_load_n / self.static_load_n


def _transient(mill: Mill, static_torque: float | None, rise_s: float, rate_hz: float,
               roll_s: float = 0.8, tail_s: float = 0.5):
    T = nominal_torque(mill) if static_torque is None else float(static_torque)
    lead = 0.2
    sc = Scenario(duration=lead + rise_s + roll_s + rise_s + tail_s,
                  bars=(Bar(t_bite=lead, t_release=lead + rise_s + roll_s, static_torque=T,
                            rise_time=rise_s, fall_time=rise_s),))
    res = simulate(mill, sc, options=ModelOptions(bearings=False), rate_hz=2000.0)
    t = np.arange(int(round(sc.duration * rate_hz)) + 1) / rate_hz
    return T, res, t


def radial_load_curve(mill: Mill, bearing_id: str, clearances_m: Sequence[float], *,
                      static_torque: float | None = None, rise_s: float = 0.02,
                      rate_hz: float = 10_000.0) -> RadialLoadCurve:
    """Largest radial load on a bearing through a bite and release, per clearance.

    Parameters
    ----------
    mill : Mill
        The torsion uses the mill file's gaps.
    bearing_id : str
    clearances_m : sequence of float
        Radial clearances to try, m.
    static_torque : float, optional
        Rolling torque, N*m reduced (default the nominal torque).
    rise_s : float
        Rise and fall time of the load, s.
    rate_hz : float
        Rate of the radial integration's output, Hz.

    Returns
    -------
    RadialLoadCurve
    """
    b = mill.bearing(bearing_id)
    T, res, t = _transient(mill, static_torque, rise_s, rate_hz)
    u = np.interp(t, res.time, res.outputs[f"tau:{b.mesh}"].to_numpy())
    from ..features.transients import static_shares

    F_static = abs(T * static_shares(mill)[b.mesh]) * b.ratio / b.base_radius
    peaks = []
    for c in clearances_m:
        r = simulate_radial(b, u, rate_hz, params={"clearance": float(c)})
        peaks.append(float(r["F"].max()))
    return RadialLoadCurve(bearing_id=bearing_id, clearances_m=np.asarray(clearances_m, float),
                           max_load_n=np.asarray(peaks), static_load_n=F_static,
                           static_torque=T)


def maintenance_clearance(curve: RadialLoadCurve, load_limit_n: float) -> float | None:
    """Smallest clearance (m) at which the largest load reaches ``load_limit_n`` (N).

    Linear interpolation between the curve's points; None when the limit is
    never reached, the first clearance when it is reached already there.
    """
    c, f = curve.clearances_m, curve.max_load_n
    above = np.flatnonzero(f >= load_limit_n)
    if above.size == 0:
        return None
    i = int(above[0])
    if i == 0:
        return float(c[0])
    return float(c[i - 1] + (load_limit_n - f[i - 1]) * (c[i] - c[i - 1]) / (f[i] - f[i - 1]))


def shaft_trajectory(mill: Mill, bearing_id: str, *, clearance_m: float | None = None,
                     static_torque: float | None = None, rise_s: float = 0.02,
                     rate_hz: float = 10_000.0) -> pd.DataFrame:
    """Shaft centre relative to the housing through a bite and a release (seed Fig. 8b).

    Returns
    -------
    DataFrame
        Index ``time_s``; ``x``, ``y`` (m, horizontal and vertical up), ``F``
        (contact force, N), ``mesh_torque`` (N*m reduced).
    """
    b = mill.bearing(bearing_id)
    _, res, t = _transient(mill, static_torque, rise_s, rate_hz)
    u = np.interp(t, res.time, res.outputs[f"tau:{b.mesh}"].to_numpy())
    p = {} if clearance_m is None else {"clearance": float(clearance_m)}
    r = simulate_radial(b, u, rate_hz, params=p)
    return pd.DataFrame({"x": r["shaft:x"].to_numpy(), "y": r["shaft:y"].to_numpy(),
                         "F": r["F"].to_numpy(), "mesh_torque": u}, index=r.index)
