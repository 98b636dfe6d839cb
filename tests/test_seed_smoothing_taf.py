"""Seed conclusions: "the peak values and TAF during transient appear to be insensitive to
the choice of smoothing function" -- checked with g3/g4 fitted to g1 by ``fit_law``.

Measured on hsm-f1, gaps a = b in C12, C34, C46, C57, one bite (TAF per element,
g1 / g3 / g4), laws fitted over +-(2.5 x static twist + gap)::

    gap 0.004, T 1e5:  C12 1.52/1.45/1.47   C34 1.83/1.60/1.65
    gap 0.004, T 4e5:  C12 1.26/1.27/1.27   C34 1.30/1.28/1.35
    gap 0.008, T 1e5:  C12 1.74/1.65/1.62   C34 2.25/1.77/1.79
    gap 0.008, T 4e5:  C12 1.34/1.34/1.37   C34 1.51/1.43/1.49

So the claim holds in the motor shaft (C12, the seed's Fig. 3 element) within 7 % at
every load, and in every element within 7 % once the static torque is large against the
gap; at low static torque with large gaps the smooth laws soften the impact in the
low-speed shafts (C34 up to 21 % lower TAF).  The tolerances below are those.
"""

from __future__ import annotations

import warnings

import pytest

from ident.model.dynamics import Family, ModelOptions
from ident.model.lawfit import fit_law
from ident.model.scenario import Bar, Scenario
from ident.model.simulate import simulate, taf_table

ELEMENTS = ("C12", "C34", "C46", "C57")


def _tafs(mill, family, T, gap):
    params = {}
    if family != "g1":
        for e in ELEMENTS:
            el = mill.element(e)
            frac = 1.0 if e in ("C12", "C34") else 0.5
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lf = fit_law(family, a=el.a, b=el.b, k1=el.k, k3=el.k,
                             amplitude=2.5 * T * frac / el.k + gap)
            params.update({f"{e}.{k}": v for k, v in lf.params.items()})
            params[f"{e}.shift"] = lf.shift
    sc = Scenario(duration=1.5, bars=(Bar(t_bite=0.2, t_release=1.4, static_torque=T),))
    r = simulate(mill, sc, options=ModelOptions(family=Family(family)), params=params)
    return taf_table(r).set_index("element")["taf"]


@pytest.mark.parametrize("gap", [0.004, 0.008])
@pytest.mark.parametrize("T", [1.0e5, 4.0e5])
def test_taf_insensitive_to_smoothing_function(mill, gap, T):
    ov = {}
    for e in ELEMENTS:
        ov[f"{e}.gap"] = gap
        ov[f"{e}.gap_open"] = gap / 2
    m = mill.with_overrides(ov)
    ref = _tafs(m, "g1", T, gap)
    for fam in ("g3", "g4"):
        taf = _tafs(m, fam, T, gap)
        assert taf["C12"] == pytest.approx(ref["C12"], rel=0.07), fam
        if T >= 4.0e5:
            for e in ELEMENTS:
                assert taf[e] == pytest.approx(ref[e], rel=0.07), (fam, e)
        else:
            for e in ELEMENTS:
                assert taf[e] == pytest.approx(ref[e], rel=0.25), (fam, e)
