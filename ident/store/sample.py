"""A small simulated rolling campaign: recordings on different days with growing wear.

What the demo, the notebook, the benchmark and the end-to-end tests run a campaign
on.  Each recording is a simulation of the mill (``ident.model.simulate``) with the
spindle gaps (and a bearing clearance) grown linearly over the campaign, written by
the real writers (``ident.io.writers``) as MCAP, or as CSV with a sibling file per
further device; a few deliberately malformed files are added.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..description import Mill

__all__ = ["SampleCampaign", "make_sample_campaign", "DEFAULT_GROWTH"]

DAY_NS = 86_400 * 10**9

#: Mill-file values at the campaign's end (they grow linearly from the mill file's).
DEFAULT_GROWTH: Mapping[str, float] = {"C46.gap": 0.0075, "C57.gap": 0.0055,
                                       "B45.clearance": 9.0e-4}


@dataclass(frozen=True)
class SampleCampaign:
    """What :func:`make_sample_campaign` wrote.

    Attributes
    ----------
    folder : Path
    good : tuple of Path
        Readable recordings (key files; CSV siblings not listed).
    bad : tuple of Path
        Malformed files.
    truth : dict
        Per good file name: ``t0_ns``, ``values`` (the overridden mill-file values),
        ``bars`` (``t_step_bite``, ``t_step_release``, ``static_torque``) and ``taf``
        (records of :func:`ident.model.simulate.taf_table`).
    """

    folder: Path
    good: tuple[Path, ...]
    bad: tuple[Path, ...]
    truth: dict[str, dict[str, Any]] = field(default_factory=dict)


def make_sample_campaign(folder: str | Path, mill: Mill, *, n_recordings: int = 8,
                         bars: int = 2, days: float = 28.0,
                         growth: Mapping[str, float] | None = None, bearings: bool = True,
                         csv_every: int = 4, n_bad: int = 2, seed: int = 0,
                         t0_ns: int | None = None, snr_db: float = 35.0,
                         mill_text: str | None = None) -> SampleCampaign:
    """Simulate a campaign of ``n_recordings`` recordings spread over ``days`` days.

    Parameters
    ----------
    folder : path
        Created if missing; recordings go to ``folder/dayNN/``.
    mill : Mill
    n_recordings, bars : int
        Recordings and bars rolled per recording.
    days : float
        Span from the first to the last recording, days.
    growth : mapping, optional
        ``{"ID.KEY": value at the end}``; values grow linearly from the mill file's.
        Default :data:`DEFAULT_GROWTH` (the keys the mill has).
    bearings : bool
        Simulate the bearings' radial model and record the accelerometers too.
    csv_every : int
        Every ``csv_every``-th recording is CSV (0: all MCAP).
    n_bad : int
        Malformed files added (a truncated MCAP, a garbage CSV, ...).
    seed : int
    t0_ns : int, optional
        Start of the first recording, ns since the Unix epoch.
    snr_db : float
        Sensor SNR.
    mill_text : str, optional
        Mill file attached to MCAP recordings.

    Returns
    -------
    SampleCampaign
    """
    from ..io.writers import write_recording
    from ..model.dynamics import ModelOptions
    from ..model.scenario import random_scenario
    from ..model.simulate import DEFAULT_T0_NS, sensor_devices, simulate, taf_table

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    t0 = DEFAULT_T0_NS if t0_ns is None else int(t0_ns)
    if growth is None:
        growth = {k: v for k, v in DEFAULT_GROWTH.items() if _has(mill, k)}
    start = {k: _value(mill, k) for k in growth}
    use_bearings = bearings and bool(mill.bearings) and bool(mill.acceleration_channels())
    good: list[Path] = []
    truth: dict[str, dict[str, Any]] = {}
    for i in range(n_recordings):
        frac = i / max(n_recordings - 1, 1)
        day = days * frac
        values = {k: start[k] + (growth[k] - start[k]) * frac for k in growth}
        m = mill.with_overrides(values) if values else mill
        rng = np.random.default_rng([seed, i])
        scenario = random_scenario(m, n_bars=bars, rng=rng)
        result = simulate(m, scenario, options=ModelOptions(bearings=use_bearings))
        start_ns = t0 + int(day * DAY_NS) + int(rng.integers(6, 18)) * 3_600 * 10**9
        devices = sensor_devices(result, rng=rng, snr_db=snr_db, t0_ns=start_ns)
        ext = ".csv" if csv_every and i % csv_every == csv_every - 1 else ".mcap"
        path = folder / f"day{int(day):02d}" / f"{mill.name}_{i:03d}{ext}"
        path.parent.mkdir(parents=True, exist_ok=True)
        kw: dict[str, Any] = {"time_format": "iso"}
        if ext == ".mcap":
            kw = {"metadata": {"mill": mill.name, "stand": mill.name, "campaign": "sample",
                               "recording_id": path.stem}}
            if mill_text:
                kw["mill_toml"] = mill_text
        write_recording(path, devices, **kw)
        good.append(path)
        truth[path.relative_to(folder).as_posix()] = {
            "t0_ns": start_ns, "values": values,
            "bars": [{"t_step_bite": b.t_step_bite, "t_step_release": b.t_step_release,
                      "static_torque": b.static_torque} for b in scenario.bars],
            "taf": taf_table(result).to_dict(orient="records")}
    bad = _malformed(folder, good, n_bad)
    return SampleCampaign(folder=folder, good=tuple(good), bad=tuple(bad), truth=truth)


def _has(mill: Mill, key: str) -> bool:
    try:
        _value(mill, key)
    except KeyError:
        return False
    return True


def _value(mill: Mill, key: str) -> float:
    ident, attr = key.split(".", 1)
    for group in (mill.elements, mill.bearings):
        for x in group:
            if x.id == ident:
                return float(getattr(x, attr))
    raise KeyError(key)


def _malformed(folder: Path, good: list[Path], n: int) -> list[Path]:
    """A truncated MCAP, a garbage CSV, an empty MCAP, a CSV of unknown channels, ..."""
    out: list[Path] = []
    bad_dir = folder / "incoming"
    src = next((p for p in good if p.suffix == ".mcap"), None)
    makers = []
    if src is not None:
        makers.append(("truncated.mcap", lambda: src.read_bytes()[: src.stat().st_size // 3]))
    makers += [
        ("garbage.csv", lambda: b"hello world\n\x00\x01 not a csv;;;\n"),
        ("empty.mcap", lambda: b""),
        ("unknown_channels.csv", lambda: b"time,T_X\n0.0,1\n0.0005,2\n0.001,3\n"),
    ]
    for name, make in makers[:n]:
        bad_dir.mkdir(parents=True, exist_ok=True)
        p = bad_dir / name
        p.write_bytes(make())
        out.append(p)
    return out
