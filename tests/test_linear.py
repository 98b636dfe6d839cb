"""Linear baseline (ident.model.linear) and ``ident frequencies`` against independent truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ident import Element, Load, Mass, Mill, Motor
from ident.cli import main
from ident.model.linear import (angles_from_deflections, damping_matrix, incidence,
                                mass_matrix, natural_modes, stiffness_matrix)

#: Seed section 2: "The torsional natural frequencies, calculated on investigated rolling
#: stand driveline, were as following: 12, 15, 20, 34, 45 and 81 Hz."
SEED_FREQUENCIES_HZ = (12.0, 15.0, 20.0, 34.0, 45.0, 81.0)


def chain(J: list[float], k: list[float], c: list[float] | None = None) -> Mill:
    """A free-free chain J[0] -k[0]- J[1] -k[1]- ... built directly from the dataclasses."""
    c = c or [0.0] * len(k)
    masses = tuple(Mass(id=f"M{i}", J=j) for i, j in enumerate(J))
    elements = tuple(Element(id=f"E{i}", from_=f"M{i}", to=f"M{i + 1}", k=ki, c=ci)
                     for i, (ki, ci) in enumerate(zip(k, c)))
    return Mill(name="chain", masses=masses, elements=elements,
                load=Load(masses=(masses[-1].id,), share=(1.0,)),
                motor=Motor(mass="M0", kp=0.0, ki=0.0), motor_speed_rpm=100.0)


def test_shipped_stand_has_the_seed_frequencies(mill):
    f = natural_modes(mill).frequencies_hz
    assert f.shape == (6,)
    np.testing.assert_allclose(f, SEED_FREQUENCIES_HZ, rtol=0.01)


def test_two_mass_free_free_closed_form():
    J1, J2, k = 1200.0, 300.0, 4.0e7
    f = natural_modes(chain([J1, J2], [k])).frequencies_hz
    # f = (1/2pi) * sqrt(k (J1 + J2) / (J1 J2))
    assert f.shape == (1,)
    assert f[0] == pytest.approx(math.sqrt(k * (J1 + J2) / (J1 * J2)) / (2 * math.pi),
                                 rel=1e-10)


def test_three_mass_chain_closed_form():
    J1, J2, J3, k1, k2 = 3000.0, 800.0, 1500.0, 5.0e7, 2.0e7
    # free-free: w**2 * (w**4 - s*w**2 + p) = 0 with
    s = k1 / J1 + k1 / J2 + k2 / J2 + k2 / J3
    p = k1 * k2 * (J1 + J2 + J3) / (J1 * J2 * J3)
    w2 = np.array([(s - math.sqrt(s * s - 4 * p)) / 2, (s + math.sqrt(s * s - 4 * p)) / 2])
    f = natural_modes(chain([J1, J2, J3], [k1, k2])).frequencies_hz
    np.testing.assert_allclose(f, np.sqrt(w2) / (2 * math.pi), rtol=1e-10)


def test_rigid_body_mode_is_left_out(mill):
    lm = natural_modes(mill)
    n = len(mill.masses)
    assert lm.frequencies_hz.shape == (n - 1,) and lm.shapes.shape == (n, n - 1)
    assert np.all(lm.frequencies_hz > 1.0)
    # the rigid rotation is in the null space of K and is M-orthogonal to every kept mode
    K, M = stiffness_matrix(mill), mass_matrix(mill)
    ones = np.ones(n)
    np.testing.assert_allclose(K @ ones, 0.0, atol=1e-6 * np.max(np.abs(K)))
    np.testing.assert_allclose(ones @ M @ lm.shapes, 0.0,
                               atol=1e-9 * np.trace(M))


def test_mode_shapes_are_m_orthogonal_eigenvectors(mill):
    lm = natural_modes(mill)
    K, M = stiffness_matrix(mill), mass_matrix(mill)
    V = lm.shapes
    G = V.T @ M @ V
    off = G - np.diag(np.diag(G))
    assert np.max(np.abs(off)) < 1e-9 * np.min(np.diag(G))
    Gk = V.T @ K @ V
    assert np.max(np.abs(Gk - np.diag(np.diag(Gk)))) < 1e-9 * np.min(np.diag(Gk))
    w2 = (2 * np.pi * lm.frequencies_hz) ** 2
    np.testing.assert_allclose(K @ V, M @ V * w2, rtol=0, atol=1e-8 * np.max(np.abs(K @ V)))
    # scaled to unit largest entry, that entry positive
    np.testing.assert_allclose(np.max(V, axis=0), 1.0)


def test_matrices_of_the_description(mill):
    D = incidence(mill)
    k = np.array([e.k for e in mill.elements])
    c = np.array([e.c for e in mill.elements])
    np.testing.assert_allclose(stiffness_matrix(mill), D.T @ np.diag(k) @ D)
    np.testing.assert_allclose(damping_matrix(mill), D.T @ np.diag(c) @ D)
    np.testing.assert_allclose(np.diag(mass_matrix(mill)), [m.J for m in mill.masses])
    K = stiffness_matrix(mill)
    np.testing.assert_allclose(K, K.T)
    assert np.all(np.linalg.eigvalsh(K) > -1e-6 * np.max(K))


def test_gaps_do_not_change_the_baseline(mill):
    # the baseline has every gap closed: wider gaps leave frequencies unchanged
    worn = mill.with_overrides({"C46.gap": 0.012, "C57.gap": 0.012})
    np.testing.assert_allclose(natural_modes(worn).frequencies_hz,
                               natural_modes(mill).frequencies_hz)


def test_modal_damping_of_a_two_mass_chain():
    J1, J2, k, c = 1000.0, 500.0, 2.0e7, 4.0e3
    lm = natural_modes(chain([J1, J2], [k], [c]))
    # single mode: zeta = c / (2 sqrt(k m_eff)), m_eff = J1 J2 / (J1 + J2)
    m_eff = J1 * J2 / (J1 + J2)
    assert lm.damping_ratios[0] == pytest.approx(c / (2 * math.sqrt(k * m_eff)), rel=1e-10)


# --- ident frequencies -----------------------------------------------------------------------

def test_cli_frequencies_json(mill_path, tmp_path, capsys):
    out = tmp_path / "freq.json"
    assert main(["frequencies", "--mill", str(mill_path), "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert {"frequencies_hz", "modes"} <= set(data)
    np.testing.assert_allclose(data["frequencies_hz"], SEED_FREQUENCIES_HZ, rtol=0.01)
    assert len(data["modes"]) == 6
    mode = data["modes"][0]
    assert mode["frequency_hz"] == pytest.approx(data["frequencies_hz"][0])
    assert set(mode["shape"]) == {"Q1", "Q2", "Q3", "Q4", "Q5", "Q6", "Q7"}
    assert set(mode["element_deflection"]) == {"C12", "C23", "C34", "C45", "C46", "C57"}
    assert capsys.readouterr().err == ""


def test_cli_frequencies_set_override(mill_path, tmp_path):
    out = tmp_path / "freq.json"
    assert main(["frequencies", "--mill", str(mill_path), "--out", str(out),
                 "--set", "C46.k=3.0e7"]) == 0
    f = json.loads(out.read_text())["frequencies_hz"]
    assert not np.allclose(f, SEED_FREQUENCIES_HZ, rtol=0.01)


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace("J = 3249.0", "J = -1.0"), "mass[Q1].J"),
    (lambda t: t.replace("[motor]", "[motor"), "not valid TOML"),
])
def test_cli_bad_mill_file_exits_2_with_one_line(mill_path, tmp_path, capsys, edit, match):
    bad = tmp_path / "bad.toml"
    bad.write_text(edit(mill_path.read_text()))
    code = main(["frequencies", "--mill", str(bad), "--out", str(tmp_path / "f.json")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.endswith("\n")
    assert err.startswith("ident frequencies: error: ")
    assert str(bad) in err and match in err
    assert not (tmp_path / "f.json").exists()


def test_cli_missing_mill_file_exits_2(tmp_path, capsys):
    missing = tmp_path / "missing.toml"
    assert main(["frequencies", "--mill", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(missing) in err and "not found" in err


def test_angles_from_deflections_inverts_the_incidence(mill):
    """On the (tree-shaped) shipped stand, D @ angles(delta) = delta, the motor at zero."""
    rng = np.random.default_rng(4)
    delta = rng.normal(scale=1e-3, size=len(mill.elements))
    im = mill.mass_index(mill.motor.mass) if hasattr(mill.motor, "mass") else 0
    theta = angles_from_deflections(mill, delta, im)
    assert theta[im] == 0.0
    np.testing.assert_allclose(incidence(mill) @ theta, delta, atol=1e-15)
