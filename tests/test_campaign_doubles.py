"""TEST DOUBLE for the per-recording pipeline (no tests in this module).

``double_process`` stands in for :func:`ident.store.process_recording` (read ->
segment -> fit -> diagnose) so that the store, campaign and report mechanics can
be tested quickly and independently of those stages.  Its "recordings" are small
JSON files (with an ``.mcap`` or ``.csv`` name) that state the truth the double
turns into dicts of the documented cli.md shapes; any file that is not such JSON
is refused with a :class:`~ident.errors.RecordingError`, as the real reader
refuses a malformed file.  Extra keys trigger the failure modes under test:
``crash`` (the worker process dies), ``sleep_s``, ``alloc_mb``, ``fail_stage``,
``no_fit`` (no fit stored, as with ``--no-fit``), ``identified`` (the elements whose
gap the fit identifies; default C46, C57, C12), ``refit_identifies`` (the elements a fit
started from a neighbour's gaps, ``Settings.starts``, identifies too).

The real pipeline is tested end to end in ``tests/test_campaign_e2e.py``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ident.description import Mill
from ident.errors import FitError, RecordingError
from ident.store.outcome import RecordingOutcome
from ident.store.process import Settings, describe_error, library_versions

DAY_NS = 86_400 * 10**9
T0_NS = 1_767_225_600_000_000_000  # 2026-01-01


def write_double_recording(path: Path, *, day: float, gaps: dict[str, float] | None = None,
                           bars: int = 2, seed: int = 0, **extra) -> Path:
    """A double "recording": JSON truth the double process function reads."""
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"double": 1, "t0_ns": int(T0_NS + day * DAY_NS), "gaps": gaps or {}, "bars": bars,
           "seed": seed, "recording_id": path.stem, **extra}
    path.write_text(json.dumps(doc))
    return path


def make_double_campaign(folder: Path, *, n: int = 6, bad: int = 1, days: float = 30.0,
                         growth_per_day: float = 1.5e-4) -> list[Path]:
    """``n`` good double recordings over ``days`` with the spindle gaps growing, ``bad`` garbage."""
    out = []
    for i in range(n):
        day = days * i / max(n - 1, 1)
        g = 0.002 + growth_per_day * day
        out.append(write_double_recording(folder / f"rec{i:03d}.mcap", day=day, seed=i,
                                          gaps={"C46": g, "C57": g * 0.9}))
    for j in range(bad):
        p = folder / f"broken{j}.mcap"
        p.write_bytes(b"\x89MCAP0\r\n" + os.urandom(64))  # truncated, garbage
        out.append(p)
    return out


def double_process(path: Path, mill: Mill, settings: Settings) -> RecordingOutcome:
    """TEST DOUBLE of ``process_recording``: JSON truth -> cli.md-shaped dicts."""
    started = time.time()
    base = dict(versions=library_versions(), started_at=started, worker=f"double:{os.getpid()}")
    try:
        doc = json.loads(Path(path).read_text())
        if doc.get("double") != 1:
            raise ValueError("not a double")
    except (ValueError, UnicodeDecodeError):
        exc = RecordingError("truncated or corrupt MCAP file (no footer)", path=str(path))
        return RecordingOutcome(status="failed", stage="read", error=describe_error("read", exc),
                                error_kind=type(exc).__name__, **base)
    if doc.get("crash"):
        os._exit(13)  # the worker process dies
    if doc.get("sleep_s"):
        time.sleep(float(doc["sleep_s"]))
    if doc.get("alloc_mb"):
        blob = np.ones(int(doc["alloc_mb"]) * 1024 * 1024 // 8)
        del blob
    rng = np.random.default_rng(doc.get("seed", 0))
    recording = {"recording_id": doc.get("recording_id"), "t0_ns": doc["t0_ns"],
                 "metadata": {"recording_id": doc.get("recording_id"), "mill": mill.name},
                 "duration_s": 10.0 * doc["bars"]}
    segments, taf = [], []
    for b in range(doc["bars"]):
        static = float(rng.uniform(1e5, 4e5))
        t = 1.0 + 10.0 * b
        segments.append({"t_start": t - 0.05, "t_step": t, "t_end": t + 1.0, "kind": "bite",
                         "static_torque": static, "step": static})
        segments.append({"t_start": t + 4.95, "t_step": t + 5.0, "t_end": t + 6.0,
                         "kind": "release", "static_torque": static, "step": -static})
        for e in ("C12", "C34", "C46", "C57"):
            g = doc["gaps"].get(e, mill.element(e).gap)
            f = 1.3 + 150.0 * g * (2e5 / static) ** 0.5
            taf.append({"transient_idx": 2 * b, "element": e, "channel": f"T_{e}",
                        "static_torque": static, "peak_torque": f * static, "taf": f})
    if doc.get("fail_stage") == "fit":
        exc = FitError("solver failed: Infeasible_Problem_Detected")
        return RecordingOutcome(status="failed", stage="fit", error=describe_error("fit", exc),
                                error_kind="FitError", recording=recording,
                                segments=tuple(segments), taf=tuple(taf), **base)
    elements = {}
    starts = dict(settings.starts)  # a refit from a neighbour's gaps
    for e in mill.elements:
        g = float(doc["gaps"].get(e.id, e.gap)) + float(rng.normal(0, 1e-4))
        elements[e.id] = {"gap": g, "gap_ci95": [g - 3e-4, g + 3e-4], "gap_open": 0.0,
                          "gap_mm": e.gap_mm(g), "params": {"a0": 1.0e7, "sigma": 900.0},
                          "identifiable": e.id in doc.get("identified", ("C46", "C57", "C12"))
                          or (e.id in starts and e.id in doc.get("refit_identifies", ()))}
    fit = {"mill": mill.name, "family": settings.family or "g3", "elements": elements,
           "metrics": {"nrmse": float(rng.uniform(0.03, 0.06)), "nrmse_linear": 0.23},
           "solver": {"status": "Solve_Succeeded", "iterations": 57, "seconds": 0.01}}

    def state(v: float, worn: float, crit: float) -> str:
        return "critical" if v > crit else "worn" if v > worn else "good"

    diag = {"elements": {k: {"state": state(v["gap"], 0.004, 0.008), "probability": 0.9,
                             "gap": v["gap"]} for k, v in elements.items()},
            "bearings": {b.id: {"state": "good", "probability": 0.88,
                                "clearance": b.clearance + 1e-5 * doc["t0_ns"] / T0_NS}
                         for b in mill.bearings},
            "features": {"frequencies_hz": [12.0, 15.0, 20.0, 34.0, 45.0, 81.0],
                         "amplitude_ratio": list(1.0 + rng.normal(0, 0.05, 6)),
                         "phase_shift_deg": list(rng.normal(0, 5, 6))}}
    quality = ({"stage": "read", "kind": "dropout", "message": "telemetry dropout of 12 ms",
                "channel": "T_C46", "t_start": 3.2, "t_end": 3.212, "fatal": False},
               ) if doc.get("seed", 0) % 3 == 1 else ()
    if doc.get("no_fit"):  # as with ``ident campaign --no-fit``
        fit = None
    return RecordingOutcome(status="done", recording=recording, segments=tuple(segments),
                            taf=tuple(taf), fit=fit, diagnosis=diag, quality=quality,
                            elapsed_s=time.time() - started, **base)
