"""Recordings with a hidden effect: test data for the discrepancy workflow.

:func:`hidden_effect_case` simulates a stand through a random rolling scenario
with one effect of effects.md at a location and strength drawn from a seed, and
hands back the recording together with the mill file the workflow is given,
which does not mention the effect.  The strengths are drawn from fixed ranges
(:data:`STRENGTHS`, chosen so that the effect is visible above sensor noise on
the torque channels), independently of anything the workflow guesses.

Besides the seven effects there are two controls: ``"none"`` (nothing
missing) and ``"sensor_filter"`` (a low-pass in one torque channel's sensor
chain, outside the library: the model cannot express it).

``backlash`` is hidden the way effects.md describes it: the recording has a
gap in an element and the mill file given to the workflow says that element is
tight (``gap = 0``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
import pandas as pd

from ..description import Mill
from ..errors import IdentError
from ..io.recording import RawDevice, Recording
from ..model.dynamics import ModelOptions
from ..model.effects import (EFFECT_NAMES, SensorFilter, typical_deflection, candidate_locations,
                             make_effect)
from ..model.scenario import Scenario, nominal_torque, random_scenario
from ..model.simulate import sensor_devices, simulate
from ..units import to_si_factor

__all__ = ["HiddenCase", "hidden_effect_case", "CONTROLS", "STRENGTHS", "recording_from_devices"]

#: Cases that are not effects: nothing missing, and a sensor-chain filter (outside the library).
CONTROLS = ("none", "sensor_filter")

#: Ranges the hidden parameters are drawn from (uniform), per effect; relative ones say so:
#: ``knee_rel`` of the nominal-load deflection beyond contact, ``amplitude_rel`` of the
#: spindle's gap, ``force_rel`` of the nominal rolling torque, ``k_rel`` of the median
#: element stiffness.  Chosen so that each effect raises the held-out nrmse of the mill
#: file's model well above the noise floor (about 0.035 at 35 dB): a named effect must
#: then lower it by 30 %.
STRENGTHS: dict[str, dict[str, tuple[float, float]]] = {
    "backlash": {"gap": (1.5e-3, 4e-3)},
    "softening_stiffness": {"knee_rel": (0.1, 0.4), "k_ratio": (0.25, 0.55)},
    "hardening_stiffness": {"knee_rel": (0.1, 0.4), "k_ratio": (2.0, 3.5)},
    "spindle_imbalance": {"amplitude_rel": (0.4, 0.9), "phase": (0.0, 2 * math.pi)},
    "coulomb_friction": {"force_rel": (0.015, 0.035), "v_smooth": (2e-3, 1e-2)},
    "strip_coupling": {"k_rel": (0.15, 0.5), "c_per_k": (1e-4, 4e-4)},
    "torque_loop_lag": {"tau": (0.006, 0.025)},
    "sensor_filter": {"cutoff_hz": (18.0, 35.0)},
}


@dataclass(frozen=True, eq=False)
class HiddenCase:
    """A simulated recording with (at most) one hidden effect.

    Attributes
    ----------
    mill : Mill
        What the workflow is given (does not mention the effect).
    truth_mill : Mill
        What was simulated (differs from ``mill`` only for ``backlash``).
    effect : str
        An effects.md name, ``"none"`` or ``"sensor_filter"``.
    location : str or None
        Element, spindle, roll pair or motor mass (channel's element for the filter).
    params : dict
        The hidden parameters (effect's local names; ``cutoff_hz`` for the filter).
    recording : Recording
        Torque channels in SI, as ``ident.io.read_recording`` would return them.
    devices : tuple of RawDevice
        The same in recorded units (to write with ``ident.io.writers.write_recording``).
    scenario : Scenario
    seed : int
    """

    mill: Mill
    truth_mill: Mill
    effect: str
    location: str | None
    params: Mapping[str, float]
    recording: Recording
    devices: tuple[RawDevice, ...]
    scenario: Scenario
    seed: int
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def expected(self) -> tuple[str | None, str | None]:
        """What a right answer names: ``(effect, location)``, or ``(None, None)`` for controls."""
        if self.effect in CONTROLS:
            return None, None
        return self.effect, self.location


def recording_from_devices(devices: tuple[RawDevice, ...], mill: Mill) -> Recording:
    """The SI recording a reader would return for ``devices`` (no file round trip)."""
    frames, rates = {}, {}
    t0 = min(d.t0_ns for d in devices)
    for d in devices:
        t = (d.t0_ns - t0) * 1e-9 + np.arange(d.n_samples) / d.rate_hz
        cols = {}
        for name, unit, row in zip(d.channels, d.units, d.data):
            ch = mill.channel(name)
            cols[name] = ((ch.scale * row + ch.offset)
                          * to_si_factor(ch.quantity.value, ch.unit)).astype(np.float32)
        frames[d.name] = pd.DataFrame(cols, index=pd.Index(t, name="time_s"))
        rates[d.name] = d.rate_hz
    return Recording(frames=frames, rates_hz=rates, t0_ns=t0, path=None,
                     metadata={"mill": mill.name})


def _draw_params(mill: Mill, effect: str, location: str, rng: np.random.Generator) -> dict:
    r = {k: float(rng.uniform(*v)) for k, v in STRENGTHS[effect].items()}
    if effect == "backlash":
        return {"gap": r["gap"]}
    if effect in ("softening_stiffness", "hardening_stiffness"):
        return {"knee": r["knee_rel"] * typical_deflection(mill, location),
                "k_ratio": r["k_ratio"]}
    if effect == "spindle_imbalance":
        return {"amplitude": r["amplitude_rel"] * mill.element(location).gap,
                "phase": r["phase"]}
    if effect == "coulomb_friction":
        return {"force": r["force_rel"] * nominal_torque(mill), "v_smooth": r["v_smooth"]}
    if effect == "strip_coupling":
        kref = float(np.median([e.k for e in mill.elements]))
        k = r["k_rel"] * kref
        return {"k": k, "c": r["c_per_k"] * k}
    if effect == "torque_loop_lag":
        return {"tau": r["tau"]}
    return r


def hidden_effect_case(mill: Mill, effect: str, *, seed: int, n_bars: int = 4,
                       location: str | None = None, params: Mapping[str, float] | None = None,
                       snr_db: float = 35.0, torque_rate_hz: float = 2000.0,
                       fluctuation: float = 0.01) -> HiddenCase:
    """Simulate a recording of ``mill`` with ``effect`` hidden in it.

    Parameters
    ----------
    mill : Mill
        The stand as its mill file describes it.
    effect : str
        An effects.md name, ``"none"`` or ``"sensor_filter"``.
    seed : int
        Seeds the location, the strength, the scenario and the sensor noise.
    n_bars : int
        Bars rolled (each gives a bite and a release).
    location, params : optional
        Fix the location or the hidden parameters instead of drawing them.
    snr_db : float
        Sensor noise below each channel's RMS, dB.
    torque_rate_hz : float
        Recorded rate, Hz.
    fluctuation : float
        Relative slow fluctuation of the rolling load.

    Returns
    -------
    HiddenCase

    Raises
    ------
    IdentError
        Unknown effect, or an effect with no location in this mill.
    """
    if effect not in EFFECT_NAMES and effect not in CONTROLS:
        raise IdentError(f"hidden_effect_case: effect must be one of "
                         f"{', '.join(EFFECT_NAMES + CONTROLS)}. Got {effect!r}.")
    rng = np.random.default_rng(seed)
    truth_mill = mill
    given = mill
    effects: tuple = ()
    filt = None
    drawn: dict[str, float] = {}
    if effect == "backlash":
        locs = mill.element_ids
    elif effect == "sensor_filter":
        locs = tuple(c.element for c in mill.torque_channels())
    elif effect == "none":
        locs = (None,)
    else:
        locs = candidate_locations(mill, effect)
    if not locs:
        raise IdentError(f"hidden_effect_case: mill '{mill.name}' has no location for "
                         f"{effect!r}.")
    loc = location if location is not None else locs[int(rng.integers(len(locs)))]
    if effect == "backlash":
        drawn = dict(params) if params else _draw_params(mill, effect, loc, rng)
        e = mill.element(loc)
        truth_mill = mill.with_overrides({f"{loc}.gap": drawn["gap"], f"{loc}.gap_open": 0.0})
        given = mill.with_overrides({f"{loc}.gap": 0.0, f"{loc}.gap_open": 0.0})
        _ = e
    elif effect == "sensor_filter":
        drawn = dict(params) if params else _draw_params(mill, effect, loc, rng)
        filt = SensorFilter(loc, cutoff_hz=drawn["cutoff_hz"])
    elif effect != "none":
        drawn = dict(params) if params else _draw_params(mill, effect, loc, rng)
        effects = (make_effect(effect, loc),)
    sc = random_scenario(mill, n_bars=n_bars, rng=rng, fluctuation=fluctuation)
    sim_params = {f"{effect}@{loc}.{k}": v for k, v in drawn.items()} if effects else {}
    res = simulate(truth_mill, sc, options=ModelOptions(bearings=False, effects=effects),
                   params=sim_params)
    if filt is not None:
        col = f"tau:{filt.channel}"
        out = res.outputs.copy()
        out[col] = filt.apply(out[col].to_numpy(), res.rate_hz)
        res = dataclasses.replace(res, outputs=out)
    channels = [c.name for c in mill.torque_channels()]
    devices = sensor_devices(res, rng=rng, snr_db=snr_db, torque_rate_hz=torque_rate_hz,
                             channels=channels)
    rec = recording_from_devices(devices, mill)
    return HiddenCase(mill=given, truth_mill=truth_mill, effect=effect,
                      location=loc, params=drawn, recording=rec, devices=devices, scenario=sc,
                      seed=seed)
