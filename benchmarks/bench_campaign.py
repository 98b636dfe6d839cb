"""Campaign throughput with 1 and 2 workers, and report time for 10,000 stored transients.

    .venv/bin/python -m benchmarks.bench_campaign [--recordings 12] [--transients 10000]

1. Simulates the sample campaign (``ident.store.make_sample_campaign``: bearings on,
   two bars per recording, MCAP and CSV) once, then runs the REAL per-recording pipeline
   (``process_recording``: read, segment, TAF and whichever of fit/diagnose are
   installed) over it into a fresh SQLite store with 1 and with 2 local worker
   processes, after a one-recording warm-up that pays the one-off start-up (imports,
   the workers' fork server; reported as ``startup``).  Throughput = recordings per
   minute of wall time, and in steady state (from the first result of each worker to
   the last); the scaling ratio is throughput(2) / throughput(1).
2. Writes ``--transients`` synthetic transients (20 per recording, with TAF, fits,
   gaps, diagnoses and features in the cli.md shapes) through ``Store.write_outcome``
   and times ``build_report`` on that store.

Results go to stdout and ``benchmarks/results/bench_campaign.json``.  The machine is
shared: the load average is printed with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ident import load_mill
from ident.report import build_report
from ident.store import (RecordingKey, RecordingOutcome, available_stages,
                         make_sample_campaign, open_store, run_campaign)

REPO = Path(__file__).resolve().parents[1]
MILL = REPO / "data" / "mills" / "hsm-f1.toml"
DAY_NS = 86_400 * 10**9


def campaign_throughput(folder: Path, mill, workers: int, tmp: Path) -> dict:
    url = f"sqlite:///{tmp}/w{workers}.db"
    stamps: list[float] = []
    t = time.perf_counter()
    s = run_campaign(folder, mill, url, workers=workers, progress=False,
                     on_stored=lambda name, o: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - t
    n = s.n_done + s.n_failed
    # steady state: after the workers have started (first result) to the last result
    steady = (60.0 * (n - workers) / (stamps[-1] - stamps[workers - 1])
              if n > workers and stamps[-1] > stamps[workers - 1] else float("nan"))
    return {"workers": workers, "recordings": n, "done": s.n_done, "failed": s.n_failed,
            "wall_s": round(wall, 2), "recordings_per_min": round(60.0 * n / wall, 1),
            "steady_recordings_per_min": round(steady, 1),
            "first_result_s": round(stamps[0] - t, 2)}


def synthetic_outcome(mill, rng: np.random.Generator, i: int, n_rec: int, per_rec: int,
                      t0_ns: int) -> RecordingOutcome:
    """A done recording with ``per_rec`` transients, in the cli.md shapes."""
    frac = i / max(n_rec - 1, 1)
    segs, taf = [], []
    for k in range(per_rec // 2):
        static = float(rng.uniform(1e5, 4e5))
        t = 2.0 + 6.0 * k
        segs += [{"t_start": t - 0.1, "t_step": t, "t_end": t + 0.6, "kind": "bite",
                  "static_torque": static, "step": static},
                 {"t_start": t + 3.9, "t_step": t + 4.0, "t_end": t + 4.5, "kind": "release",
                  "static_torque": static, "step": -static}]
        for ch in mill.torque_channels():
            f = 1.2 + 0.3 * frac + 3e4 / static * float(rng.uniform(0.9, 1.1))
            taf.append({"transient_idx": 2 * k, "element": ch.element, "channel": ch.name,
                        "static_torque": static, "peak_torque": f * static, "taf": f})
    elements = {}
    for e in mill.elements:
        g = e.gap + (0.004 if e.id in ("C46", "C57") else 0.0) * frac + rng.normal(0, 2e-4)
        elements[e.id] = {"gap": g, "gap_ci95": [g - 4e-4, g + 4e-4], "gap_open": 0.0,
                          "gap_mm": e.gap_mm(g), "params": {"a0": 1e7, "sigma": 900.0}}
    fit = {"mill": mill.name, "family": "g3", "elements": elements,
           "metrics": {"nrmse": 0.04, "nrmse_linear": 0.2},
           "solver": {"status": "Solve_Succeeded", "iterations": 50, "seconds": 3.0}}
    diag = {"elements": {k: {"state": "good", "probability": 0.9, "gap": v["gap"]}
                         for k, v in elements.items()},
            "bearings": {b.id: {"state": "good", "probability": 0.9,
                                "clearance": b.clearance + 5e-4 * frac}
                         for b in mill.bearings},
            "features": {"frequencies_hz": [12.0, 15.0, 20.0, 34.0, 45.0, 81.0],
                         "amplitude_ratio": list(1 + rng.normal(0, 0.05, 6)),
                         "phase_shift_deg": list(rng.normal(0, 5, 6))}}
    return RecordingOutcome(status="done", segments=tuple(segs), taf=tuple(taf), fit=fit,
                            diagnosis=diag,
                            recording={"t0_ns": t0_ns + int(60 * frac * DAY_NS),
                                       "recording_id": f"syn{i:05d}", "duration_s": 120.0},
                            started_at=time.time(), elapsed_s=1.0)


def report_time(mill, n_transients: int, tmp: Path, per_rec: int = 20) -> dict:
    url = f"sqlite:///{tmp}/report.db"
    rng = np.random.default_rng(0)
    n_rec = max(1, n_transients // per_rec)
    t = time.perf_counter()
    with open_store(url) as st:
        st.register_mill(mill, MILL.read_text())
        run = st.start_run(directory="synthetic", mill=mill, settings_hash="s" * 64,
                           settings={}, executor="synthetic", host="bench", versions={},
                           n_found=n_rec, n_skipped=0)
        for i in range(n_rec):
            o = synthetic_outcome(mill, rng, i, n_rec, per_rec, 1_767_225_600_000_000_000)
            st.write_outcome(run, RecordingKey(f"syn/{i:05d}.mcap", f"{i:064x}", "s" * 64), o,
                             mill=mill, files=[f"syn/{i:05d}.mcap"], size_bytes=1)
        st.finish_run(run, status="finished", n_done=n_rec, n_failed=0)
        n_tr = st.count("transients")
    insert_s = time.perf_counter() - t
    t = time.perf_counter()
    r = build_report(url, tmp / "report.html")
    rep_s = time.perf_counter() - t
    return {"recordings": n_rec, "transients": n_tr, "insert_s": round(insert_s, 2),
            "report_s": round(rep_s, 2),
            "report_bytes": (tmp / "report.html").stat().st_size,
            "statuses": sorted({a.status for _, a in r.assessments})}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_campaign")
    p.add_argument("--recordings", type=int, default=12)
    p.add_argument("--transients", type=int, default=10_000)
    args = p.parse_args(argv)
    mill = load_mill(MILL)
    out: dict = {"load_average_start": os.getloadavg(), "cores": os.cpu_count(),
                 "stages": ["read", "segment", "taf", *available_stages()]}
    with tempfile.TemporaryDirectory(prefix="ident-bench-") as d:
        tmp = Path(d)
        t = time.perf_counter()
        sample = make_sample_campaign(tmp / "campaign", mill, n_recordings=args.recordings,
                                      bars=2, days=28.0, n_bad=0)
        out["simulate_s"] = round(time.perf_counter() - t, 1)
        # one-off start-up: store, stage imports and the workers' fork server
        warm = make_sample_campaign(tmp / "warm", mill, n_recordings=1, bars=1, n_bad=0,
                                    bearings=False)
        out["startup"] = campaign_throughput(warm.folder, mill, 1, tmp)
        runs = [campaign_throughput(sample.folder, mill, w, tmp) for w in (1, 2)]
        out["campaign"] = runs
        out["scaling_ratio"] = round(runs[1]["recordings_per_min"] /
                                     runs[0]["recordings_per_min"], 2)
        out["scaling_ratio_steady"] = round(runs[1]["steady_recordings_per_min"] /
                                            runs[0]["steady_recordings_per_min"], 2)
        out["report"] = report_time(mill, args.transients, tmp)
    out["load_average_end"] = os.getloadavg()
    print(json.dumps(out, indent=1))
    res = REPO / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "bench_campaign.json").write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
