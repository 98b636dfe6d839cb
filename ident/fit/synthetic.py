"""Simulated recordings with known gaps: the truth the fit is tested and benchmarked on.

:func:`synthetic_case` draws nothing itself: it rolls a random scenario
(:func:`ident.model.scenario.random_scenario`: static torque varying per bar,
a slow fluctuation of the rolling load) through the driveline of a mill with
the given gaps, records it as the telemetry would (:func:`ident.model.simulate.
sensor_devices`: white noise at ``snr_db``, 16-bit quantisation), writes and
reads it back (``.mcap``), segments it and cuts the fit windows -- the same
path as ``ident fit``.  :func:`random_gaps` draws a gap state from a seed.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..description import Mill
from .windows import FitWindow, windows_from_recording

__all__ = ["SyntheticCase", "synthetic_case", "random_gaps"]


@dataclass(frozen=True, eq=False)
class SyntheticCase:
    """A simulated recording, its fit windows and the truth behind them.

    Attributes
    ----------
    mill : Mill
        The simulated (true) mill: the mill file with the drawn gaps.
    windows : tuple of FitWindow
    truth : mapping
        Per element ``{"gap": rad, "gap_open": rad}`` (reduced).
    path : Path
        The written recording.
    segments : tuple
        What the segmenter found.
    scenario : Scenario
    """

    mill: Mill
    windows: tuple[FitWindow, ...]
    truth: Mapping[str, Mapping[str, float]]
    path: Path
    segments: tuple
    scenario: Any
    states: tuple = ()

    def true_estimate(self, problem: Any) -> Any:
        """The truth as a point of ``problem``'s parameter space (g1).

        Shared gaps from :attr:`truth`; per window the simulated state at its
        first sample moved to the fit's convention (drive-side contact at
        ``delta = 0``, motor angle 0) and the scenario's load step (level
        before and after, half-height time, rise; no slopes).  A start at the
        truth, for tests of what happens *at* the optimum (interval coverage)
        apart from the search for it.
        """
        from ..model.linear import incidence
        from ..model.linear import angles_from_deflections
        from .problem import Estimate

        m = problem.model
        mill = self.mill
        n = len(mill.masses)
        D = incidence(mill)
        b = np.array([e.gap_open for e in mill.elements])
        X0, W = [], []
        for w in problem.windows:
            X = dict(self.states)[w.label]
            theta = angles_from_deflections(mill, D @ X[:n] - b, m.motor_index)
            x0 = np.array(X[:m.nx], dtype=float)
            x0[:n] = theta
            X0.append(x0)
            steps = []
            for bar in self.scenario.bars:
                steps.append((bar.t_step_bite, 0.0, bar.static_torque, bar.rise_time))
                steps.append((bar.t_step_release, bar.static_torque, 0.0, bar.fall_time))
            ts, L0, L1, rise = min(steps, key=lambda st: abs(st[0] - w.t_step))
            row = np.zeros(m.n_window)  # skew, ramp weights, offsets 0: it has none
            row[:6] = [L0 + self.scenario.idle_torque, L1 + self.scenario.idle_torque,
                       ts - w.t[0], rise, 0.0, 0.0]
            for eid in m.kgap_elements:
                row[m.window_names.index(f"{eid}.open_frac")] = 0.5
            W.append(row)
        shared = np.zeros(m.n_shared)  # drag 0: this generator's idle torque acts on the rolls
        for e in mill.elements:
            shared[m.shared_names.index(f"{e.id}.gap")] = self.truth[e.id]["gap"]
        return Estimate(shared=shared, window=np.array(W), x0=np.array(X0))


def random_gaps(mill: Mill, rng: np.random.Generator, *,
                elements: Sequence[str] | None = None,
                gap_range: tuple[float, float] = (1e-3, 8e-3),
                closed: Sequence[str] = ()) -> dict[str, float]:
    """Mill-file overrides of a random worn state.

    Every element of ``elements`` (default: all) gets a total gap drawn
    log-uniform from ``gap_range`` (rad) and an open part uniform in
    ``[0, gap]``; elements in ``closed`` get a zero gap.

    Returns
    -------
    dict
        ``{"C46.gap": ..., "C46.gap_open": ...}`` for :meth:`Mill.with_overrides`.
    """
    ids = list(mill.element_ids) if elements is None else list(elements)
    out: dict[str, float] = {}
    lo, hi = np.log(gap_range[0]), np.log(gap_range[1])
    for eid in ids:
        if eid in closed:
            g = 0.0
        else:
            g = float(np.exp(rng.uniform(lo, hi)))
        out[f"{eid}.gap"] = g
        out[f"{eid}.gap_open"] = float(rng.uniform(0.0, g)) if g > 0 else 0.0
    for eid in closed:
        out[f"{eid}.gap"] = 0.0
        out[f"{eid}.gap_open"] = 0.0
    return out


def synthetic_case(mill: Mill, overrides: Mapping[str, float] | None = None, *, seed: int = 0,
                   n_bars: int = 2, snr_db: float = 35.0, fluctuation: float = 0.01,
                   window_s: float = 0.6, max_windows: int | None = 4,
                   kinds: Sequence[str] = ("bite", "release"),
                   rolling_s: tuple[float, float] = (0.8, 1.2),
                   idle_s: tuple[float, float] = (0.8, 1.2),
                   directory: str | Path | None = None) -> SyntheticCase:
    """Simulate, record, read back, segment and window a recording of known gaps.

    Parameters
    ----------
    mill : Mill
        The mill file (designed gaps).
    overrides : mapping, optional
        The true state, e.g. from :func:`random_gaps`.
    seed : int
        Seed of the scenario (static torques 25-100 % of nominal, rise times,
        load fluctuation) and of the sensor noise.
    n_bars : int
    snr_db : float
        Sensor SNR, dB below each channel's RMS.
    fluctuation : float
        Relative fluctuation of the rolling load (0.2-2 Hz).
    window_s, max_windows, kinds
        As :func:`ident.fit.windows_from_recording`.
    rolling_s, idle_s : (float, float)
        Rolling and idle time ranges per bar, s (short: quick to simulate).
    directory : path, optional
        Where the recording goes (default: a new temporary directory).

    Returns
    -------
    SyntheticCase
    """
    from ..io.readers import read_recording
    from ..io.writers import write_recording
    from ..model.dynamics import ModelOptions
    from ..model.scenario import random_scenario
    from ..model.simulate import sensor_devices, simulate
    from ..segment import segment_transients

    true = mill.with_overrides(dict(overrides)) if overrides else mill
    rng = np.random.default_rng(seed)
    sc = random_scenario(true, n_bars=n_bars, rng=rng, fluctuation=fluctuation,
                         rolling_s=rolling_s, idle_s=idle_s)
    res = simulate(true, sc, options=ModelOptions(bearings=False))
    devices = sensor_devices(res, rng=rng, snr_db=snr_db)
    d = Path(tempfile.mkdtemp(prefix="ident-fit-")) if directory is None else Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"synthetic-{seed}.mcap"
    write_recording(path, devices, metadata={"mill": true.name, "recording_id": path.stem,
                                             "campaign": "synthetic"})
    rec = read_recording(path, true, warn=False)
    segs = segment_transients(rec, true)
    windows = windows_from_recording(rec, true, segs, window_s=window_s,
                                     max_windows=max_windows, kinds=kinds)
    truth = {e.id: {"gap": float(e.gap), "gap_open": float(e.gap_open)} for e in true.elements}
    Xs = res.states.to_numpy()
    states = tuple((w.label, Xs[int(round(w.t[0] * res.rate_hz))].copy()) for w in windows)
    return SyntheticCase(mill=true, windows=windows, truth=truth, path=path,
                         segments=tuple(segs), scenario=sc, states=states)
