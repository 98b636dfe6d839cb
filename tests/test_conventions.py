"""The sign conventions written in ident/description.py's docstring (and mill-config.md).

* delta = theta_from - theta_to (reduced), through ``ident.model.linear.incidence``;
  the ``from`` mass feels minus the element torque, the ``to`` mass plus;
* positive torque drives the rolls: a positive deflection beyond ``b`` gives a
  positive restoring torque, and a motor driving against the rolling load
  deflects every element positively;
* the gap follows seed Fig. 1a: ``a = gap - gap_open`` on the negative side,
  ``b = gap_open`` on the drive (positive) side;
* ``gap_mm = gap_rad / ratio * radius * 1000``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ident import Element
from ident.model.laws import element_torque_law
from ident.model.linear import incidence, stiffness_matrix


def test_deflection_is_from_minus_to(mill):
    D = incidence(mill)
    theta = np.arange(1.0, len(mill.masses) + 1) ** 2  # distinct angles, rad
    delta = D @ theta
    for e, d in zip(mill.elements, delta):
        i, j = mill.mass_index(e.from_), mill.mass_index(e.to)
        assert d == theta[i] - theta[j]
    assert (mill.element("C46").from_, mill.element("C46").to) == ("Q4", "Q6")
    assert delta[mill.element_ids.index("C46")] == theta[3] - theta[5]


def test_from_mass_feels_minus_the_torque_to_mass_plus(mill):
    D = incidence(mill)
    tau = np.zeros(len(mill.elements))
    tau[mill.element_ids.index("C12")] = 1.0e5  # N*m transmitted from Q1 to Q2
    on_masses = -D.T @ tau
    assert on_masses[mill.mass_index("Q1")] == -1.0e5
    assert on_masses[mill.mass_index("Q2")] == 1.0e5
    assert np.count_nonzero(on_masses) == 2


def test_positive_deflection_beyond_b_gives_driving_torque():
    e = Element(id="C", from_="A", to="B", k=2.0e7, gap=0.003, gap_open=0.001)
    assert element_torque_law(e, e.b + 1e-4) == pytest.approx(2.0e7 * 1e-4)
    assert element_torque_law(e, -e.a - 1e-4) == pytest.approx(-2.0e7 * 1e-4)


def test_gap_a_on_negative_side_b_on_positive_side():
    e = Element(id="C", from_="A", to="B", k=2.0e7, gap=0.003, gap_open=0.001)
    assert (e.a, e.b) == pytest.approx((0.002, 0.001))
    inside = np.linspace(-0.002, 0.001, 31)
    np.testing.assert_array_equal(element_torque_law(e, inside), 0.0)
    assert element_torque_law(e, 0.0011) > 0     # drive side closes after b = gap_open
    assert element_torque_law(e, -0.0021) < 0    # the closed part a lies on the negative side
    assert element_torque_law(e, -0.0011) == 0.0  # ... so -b is still inside the gap


def test_shipped_couplings_start_closed_on_the_drive_side(mill):
    # hsm-f1: gap_open = 0, so b = 0 and driving torque is carried at once
    for e in mill.elements:
        assert e.b == 0.0 and e.a == e.gap
        assert element_torque_law(e, 1e-5) == pytest.approx(e.k * 1e-5)
        assert element_torque_law(e, -e.gap / 2) == 0.0


def test_motor_driving_the_rolling_load_deflects_every_element_positively(mill):
    # static equilibrium of the baseline: +T on the motor rotor, -T shared by the load masses
    T = 1.0e5
    F = np.zeros(len(mill.masses))
    F[mill.mass_index(mill.motor.mass)] = T
    for m, s in zip(mill.load.masses, mill.load.share):
        F[mill.mass_index(m)] -= s * T
    theta, *_ = np.linalg.lstsq(stiffness_matrix(mill), F, rcond=None)
    delta = incidence(mill) @ theta
    tau = np.array([element_torque_law(e, d) for e, d in zip(mill.elements, delta)])
    # gaps closed on the drive side, so the torque is k*delta and positive everywhere
    assert np.all(delta > 0) and np.all(tau > 0)
    torque = dict(zip(mill.element_ids, tau))
    for eid in ("C12", "C23", "C34"):
        assert torque[eid] == pytest.approx(T)
    for eid in ("C45", "C46", "C57"):
        assert torque[eid] == pytest.approx(T / 2)


def test_gap_mm_formula(mill):
    c46 = mill.element("C46")  # ratio 2.5, radius 0.5 m
    assert c46.gap_mm() == pytest.approx(0.002 / 2.5 * 0.5 * 1000)
    # the seed's "2.5 mm wear in spindles" as the mill file's comment has it: 0.012 rad -> 2.4 mm
    assert c46.gap_mm(0.012) == pytest.approx(2.4)
    c12 = mill.element("C12")  # ratio 1
    assert c12.gap_mm(0.004) == pytest.approx(0.004 * 0.35 * 1000)
    assert dataclasses.replace(c46, radius=None).gap_mm() is None
