"""Bearings (seed section 2.2, Fig. 8): the free-parameter radial model against the
simulator's, the shaft-centre trajectory and the maximum radial load against clearance."""

from __future__ import annotations

import numpy as np
import pytest

from ident.diagnose import maintenance_clearance, radial_load_curve, shaft_trajectory
from ident.diagnose.radial import simulate_radial
from ident.model.scenario import Bar, Scenario, nominal_torque
from ident.model.simulate import simulate


def test_radial_model_agrees_with_the_simulator(mill):
    """Same equations as ident.model.dynamics' bearing block, driven by its mesh torque.

    The shaft rattles in its clearance after the bite (an impact oscillator), so
    the comparison is of the force history over the bite and of the vibration
    level, not sample by sample over seconds.
    """
    sc = Scenario(duration=1.2, bars=(Bar(0.2, 0.9, 250e3, 0.02, 0.02),))
    full = simulate(mill, sc)
    out = full.outputs
    b = mill.bearing("B23")
    r = simulate_radial(b, out[f"tau:{b.mesh}"].to_numpy(), full.rate_hz)
    bite = (full.time > 0.15) & (full.time < 0.3)
    F_full = out["F:B23"].to_numpy()
    assert np.max(np.abs(r["F"].to_numpy()[bite] - F_full[bite])) < 0.05 * F_full[bite].max()
    rms = lambda x: float(np.sqrt(np.mean(x ** 2)))  # noqa: E731
    a_full = out["acc:B23:v"].to_numpy()[bite]
    assert rms(r["acc:v"].to_numpy()[bite]) == pytest.approx(rms(a_full), rel=0.15)
    # at rest before the bite: shaft on the bottom of its clearance, pressed in by its weight
    sag = b.shaft_mass * 9.80665 / b.k_bearing
    assert r["shaft:y"].iloc[0] == pytest.approx(-b.clearance - sag, rel=1e-6)
    assert out["shaft:B23:y"].iloc[0] == pytest.approx(r["shaft:y"].iloc[0], rel=1e-9)


def test_shaft_trajectory_stays_in_its_clearance(mill):
    """Seed Fig. 8b: the shaft starts at the bottom and moves within the clearance,
    beyond it only by the contact deformation (of the order of F/k_bearing: tenths of
    a millimetre at MN loads; the contact damper lets it exceed F/k on rebound)."""
    b = mill.bearing("B23")
    c = 1.0e-3
    tr = shaft_trajectory(mill, "B23", clearance_m=c)
    r = np.hypot(tr["x"], tr["y"])
    assert tr["y"].iloc[0] == pytest.approx(-c - b.shaft_mass * 9.80665 / b.k_bearing, rel=1e-6)
    assert np.all(r <= c + 3.0 * tr["F"].max() / b.k_bearing)
    assert tr["y"].max() > 0.5 * c  # the mesh force lifts it across the clearance


def test_radial_load_grows_with_clearance(mill):
    """Seed Fig. 8c: the largest radial load grows with the bearing clearance.

    Measured on the shipped stand, bite and release at the nominal 400 kN*m, 20 ms
    ramps, mill-file gaps: B23 (gearbox mesh, static mesh load 1600 kN) reaches
    about 1.96 MN at 0.2 mm, 2.34 MN at 1.0 mm, 2.73 MN at 1.8 mm and 3.57 MN at
    3 mm; B45 (pinion stand, 1316 kN static) 1.79, 2.53, 3.56 and 4.20 MN.  The
    seed's 1000 kN limit lies below our static mesh loads (our stand is heavier
    loaded), so as a maintenance point we read a dynamic load limit instead:
    1.7 times the static load (2.72 MN) is crossed at about 1.8 mm on B23 --
    the mill file's ``clearance_critical`` -- as the seed's 1000 kN at 1.8 mm.
    """
    cl = np.array([0.2e-3, 1.0e-3, 1.8e-3, 3.0e-3])
    curve = radial_load_curve(mill, "B23", cl)
    assert curve.static_torque == pytest.approx(nominal_torque(mill))
    assert curve.static_load_n == pytest.approx(1.6e6, rel=1e-3)
    assert np.all(curve.max_load_n > curve.static_load_n)
    assert curve.max_load_n[-1] > 1.5 * curve.max_load_n[0]
    assert curve.max_load_n[2] == pytest.approx(2.73e6, rel=0.05)
    # the seed's 1000 kN is exceeded at any clearance here
    assert maintenance_clearance(curve, 1.0e6) == pytest.approx(cl[0])
    point = maintenance_clearance(curve, 1.7 * curve.static_load_n)
    assert point is not None and 1.4e-3 < point < 2.2e-3
    assert maintenance_clearance(curve, 10e6) is None
