"""Rolling scenarios: bars with bite and release load steps (the simulator's input).

A bar's rolling torque rises at the bite over ``rise_time`` (a raised-cosine
ramp, 10-40 ms in real mills), holds its static level with a slow random
fluctuation (temperature and friction in the roll gap), and falls at the
release.  ``t_step`` (cli.md) is the instant the load reaches half its height.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..description import Mill

__all__ = ["Bar", "Scenario", "load_profile", "random_scenario", "nominal_torque"]


@dataclass(frozen=True)
class Bar:
    """One rolled bar.

    Attributes
    ----------
    t_bite : float
        Start of the load rise, s.
    t_release : float
        Start of the load fall, s (after the rise has ended).
    static_torque : float
        Rolling torque, N*m reduced to the motor shaft (total over load masses).
    rise_time, fall_time : float
        Durations of the raised-cosine ramps, s.
    """

    t_bite: float
    t_release: float
    static_torque: float
    rise_time: float = 0.02
    fall_time: float = 0.02

    @property
    def t_step_bite(self) -> float:
        """Half-height instant of the bite load step, s."""
        return self.t_bite + 0.5 * self.rise_time

    @property
    def t_step_release(self) -> float:
        """Half-height instant of the release load step, s."""
        return self.t_release + 0.5 * self.fall_time


@dataclass(frozen=True)
class Scenario:
    """A recording's worth of bars.

    Attributes
    ----------
    duration : float
        Seconds.
    bars : tuple of Bar
    idle_torque : float
        Load between bars (bearing friction), N*m reduced.
    fluctuation : float
        Relative standard deviation of the rolling load around its static level.
    fluctuation_hz : float
        Bandwidth of that fluctuation, Hz.
    seed : int
        Seed of the fluctuation (the scenario is deterministic).
    """

    duration: float
    bars: tuple[Bar, ...]
    idle_torque: float = 0.0
    fluctuation: float = 0.0
    fluctuation_hz: float = 2.0
    seed: int = 0


def _ramp(s: np.ndarray) -> np.ndarray:
    """Raised cosine from 0 (s <= 0) to 1 (s >= 1)."""
    s = np.clip(s, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(np.pi * s))


def load_profile(scenario: Scenario, t: np.ndarray) -> np.ndarray:
    """Rolling torque at times ``t`` (s, any shape), N*m reduced, positive against rotation."""
    t_in = np.asarray(t, dtype=float)
    t = t_in.ravel()
    T = np.full_like(t, scenario.idle_torque)
    rng = np.random.default_rng(scenario.seed)
    for bar in scenario.bars:
        on = _ramp((t - bar.t_bite) / bar.rise_time) * (1.0 - _ramp((t - bar.t_release) /
                                                                    bar.fall_time))
        level = bar.static_torque
        if scenario.fluctuation > 0:
            # a few random sinusoids below fluctuation_hz, unit variance overall
            k = 6
            f = rng.uniform(0.2, 1.0, k) * scenario.fluctuation_hz
            ph = rng.uniform(0, 2 * np.pi, k)
            wav = np.sqrt(2.0 / k) * np.sum(np.sin(2 * np.pi * f[:, None] * (t - bar.t_bite)[None]
                                                   + ph[:, None]), axis=0)
            level = level * (1.0 + scenario.fluctuation * wav)
        T = T + on * level
    return T.reshape(t_in.shape)


def nominal_torque(mill: Mill) -> float:
    """A typical full rolling torque of the stand, N*m reduced.

    40 % of the motor's torque limit when the mill file gives one; otherwise the
    torque that twists the softest element by 5 mrad.
    """
    if mill.motor.torque_limit is not None:
        return 0.4 * mill.motor.torque_limit
    return 5e-3 * min(e.k for e in mill.elements)


def random_scenario(mill: Mill, *, n_bars: int, rng: np.random.Generator,
                    torque_range: tuple[float, float] | None = None,
                    rolling_s: tuple[float, float] = (1.5, 3.0),
                    idle_s: tuple[float, float] = (1.0, 2.0),
                    rise_s: tuple[float, float] = (0.01, 0.04), lead_s: float = 0.5,
                    fluctuation: float = 0.01) -> Scenario:
    """Draw ``n_bars`` bars of varying static torque, rolling and idle times.

    Parameters
    ----------
    mill : Mill
    n_bars : int
    rng : numpy.random.Generator
    torque_range : (float, float), optional
        Static torque range, N*m reduced; default 25-100 % of :func:`nominal_torque`.
    rolling_s, idle_s, rise_s : (float, float)
        Ranges of the rolling time, the pause after a bar and the rise/fall time, s.
    lead_s : float
        Idle time before the first bite, s.
    fluctuation : float
        Relative load fluctuation while rolling.
    """
    lo, hi = torque_range or (0.25 * nominal_torque(mill), nominal_torque(mill))
    t = lead_s
    bars = []
    for _ in range(n_bars):
        rise = float(rng.uniform(*rise_s))
        fall = float(rng.uniform(*rise_s))
        roll = float(rng.uniform(*rolling_s))
        bars.append(Bar(t_bite=t, t_release=t + rise + roll, static_torque=float(rng.uniform(lo, hi)),
                        rise_time=rise, fall_time=fall))
        t = t + rise + roll + fall + float(rng.uniform(*idle_s))
    return Scenario(duration=t, bars=tuple(bars), fluctuation=fluctuation,
                    seed=int(rng.integers(2 ** 31)))
