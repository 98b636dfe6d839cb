"""Benchmark: gap identification by direct collocation against single shooting.

Issue 4's benchmark, in one run, on the same simulated recordings of the
shipped stand (``data/mills/hsm-f1.toml``; C12 1.0, C34 1.5, C46 6.0, C57 4.0
mrad of total gap, C23 and C45 0.5 mrad; 35 dB sensor noise, the rolling
load fluctuating 1 %), each method from the same start (the mill file's
designed gaps, the same linear baseline, the same settling and continuation
on the smoothing width; collocation also continues on the fitted horizon, which
shooting does not need and which only slows it down):

(a) one 0.6 s bite, (b) five bites fitted jointly, (c) success rate from 20
poor initial guesses (log-uniform 0.3-15 mrad for every element) on a bite
and a release, (d) one 3 s window that includes the idle rattle after a
release; then how collocation's time grows with the window length and the
number of windows.  Shooting is ``scipy.optimize.least_squares`` over a
CasADi RK4 (one step per sample) with forward sensitivities -- the baseline
every ratio is measured against in the same run.

Each fit runs in a fresh child process so that its peak resident memory is
its own.  "Accuracy" is the largest error of the gaps the fit reports as
identifiable against the truth, and the largest difference between the two
methods' gaps; "success" is a converged solve with every directly measured
element (C12, C34, C46, C57) within max(10 %, 0.3 mrad) of its truth.

Run:  nice .venv/bin/python -m benchmarks.bench_fit [--quick] [--only a,b,c,d,scale]

Expect more than an hour: (a) about 15 s, (b) 5 min, (c) 40 s per start and
method, (d) over 30 min for collocation on the 3 s window (the rattle after a
release makes the NLP hard; a 0.6 s release alone took 561 s), the scaling
part 10 min.  ``--only a,b,c --quick`` takes about 10 minutes.

Results go to stdout and to ``benchmarks/results/bench_fit.json``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MILL = ROOT / "data" / "mills" / "hsm-f1.toml"
TRUTH = {"C12.gap": 0.001, "C12.gap_open": 0.0005, "C34.gap": 0.0015, "C34.gap_open": 0.0005,
         "C46.gap": 0.006, "C46.gap_open": 0.003, "C57.gap": 0.004, "C57.gap_open": 0.001}
MEASURED = ("C12", "C34", "C46", "C57")


def _case(kind: str, *, seed: int = 7, window_s: float = 0.6, n: int = 1) -> Any:
    from ident import load_mill
    from ident.fit.synthetic import synthetic_case

    mill = load_mill(MILL)
    kinds = {"bite": ("bite",), "release": ("release",), "both": ("bite", "release")}[kind]
    idle = (window_s + 0.6, window_s + 0.8)
    bars = n if kind != "both" else max(1, (n + 1) // 2)
    return mill, synthetic_case(mill, TRUTH, seed=seed, n_bars=bars, window_s=window_s,
                                max_windows=n, kinds=kinds, idle_s=idle,
                                rolling_s=(max(0.8, window_s + 0.2), max(1.0, window_s + 0.4)))


def _fit(job: dict) -> dict:
    """One fit (in a child process): time, iterations, size, peak memory, accuracy."""
    warnings.simplefilter("ignore")
    from ident.fit import Collocation, SingleShooting, fit_gaps

    mill, case = _case(job["kind"], seed=job.get("seed", 7), window_s=job["window_s"],
                       n=job["n"])
    method = Collocation() if job["method"] == "collocation" else SingleShooting()
    kw = {"starts": [job["start"]]} if job.get("start") else {}
    t, cpu = time.perf_counter(), time.process_time()
    res = fit_gaps(mill, case.windows, method=method, uncertainty=job.get("uncertainty", True),
                   **kw)
    wall = time.perf_counter() - t
    cpu = time.process_time() - cpu
    truth = {k: v["gap"] for k, v in case.truth.items()}
    err_id = [abs(e.gap - truth[k]) for k, e in res.elements.items() if e.identifiable]
    opens = {k: v["gap_open"] for k, v in case.truth.items()}
    err_open = [abs(e.gap_open - opens[k]) for k, e in res.elements.items()
                if e.gap_open_identifiable]
    ok = res.converged and all(
        abs(res.elements[k].gap - truth[k]) <= max(0.1 * truth[k], 3e-4) for k in MEASURED)
    return {"method": job["method"], "kind": job["kind"], "n_windows": len(case.windows),
            "samples": int(sum(w.n_samples for w in case.windows)), "wall_s": round(wall, 2),
            "cpu_s": round(cpu, 2), "build_s": round(res.solver.build_seconds, 2),
            "iterations": res.solver.iterations, "status": res.solver.status,
            "converged": res.converged, "success": bool(ok),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "nlp": dict(res.solver.nlp), "gaps": res.gaps(),
            "identifiable": {k: e.identifiable for k, e in res.elements.items()},
            "max_err_identifiable_urad": round(1e6 * max(err_id), 1) if err_id else None,
            "n_identifiable": len(err_id), "n_open_identifiable": len(err_open),
            "max_err_open_urad": round(1e6 * max(err_open), 1) if err_open else None,
            "gaps_open": {k: e.gap_open for k, e in res.elements.items()},
            "nrmse": res.nrmse, "nrmse_linear": res.nrmse_linear}


def _run(job: dict) -> dict:
    ctx = mp.get_context("spawn")
    with ctx.Pool(1) as pool:
        return pool.apply(_fit, (job,))


def _pair(label: str, job: dict) -> dict:
    out = {}
    for method in ("shooting", "collocation"):
        r = _run(dict(job, method=method))
        out[method] = r
        print(f"  {label:<28} {method:<12} {r['wall_s']:7.1f} s wall {r['cpu_s']:7.1f} s cpu "
              f"{r['iterations']:5d} it  {r['peak_rss_mb']:7.0f} MB  {r['status'][:28]:<28} "
              f"gap err {r['max_err_identifiable_urad']} urad "
              f"({r['n_identifiable']} identifiable), "
              f"open err {r['max_err_open_urad']} urad ({r['n_open_identifiable']})", flush=True)
    s, c = out["shooting"], out["collocation"]
    gs, gc = s["gaps"], c["gaps"]
    out["ratio_wall"] = round(c["wall_s"] / max(s["wall_s"], 1e-9), 2)
    out["max_gap_difference_urad"] = round(1e6 * max(abs(gs[k] - gc[k]) for k in MEASURED), 1)
    out["max_open_difference_urad"] = round(1e6 * max(
        abs(s["gaps_open"][k] - c["gaps_open"][k]) for k in MEASURED), 1)
    print(f"  {label:<28} collocation / shooting = {out['ratio_wall']}x wall; methods differ "
          f"by at most {out['max_gap_difference_urad']} urad in gap, "
          f"{out['max_open_difference_urad']} urad in open part on the measured elements "
          "(a bite from rest shows the open parts only)", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_fit",
                                description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="5 poor starts instead of 20")
    p.add_argument("--only", default="a,b,c,d,scale", help="comma-separated parts to run")
    p.add_argument("--starts", type=int, default=20)
    args = p.parse_args(argv)
    parts = set(args.only.split(","))
    out: dict[str, Any] = {"load_average_start": os.getloadavg(), "cores": os.cpu_count()}
    print(f"bench_fit: load average {out['load_average_start']}", flush=True)
    if "a" in parts:
        print("(a) one 0.6 s bite", flush=True)
        out["a_one_bite"] = _pair("one bite 0.6 s", {"kind": "bite", "window_s": 0.6, "n": 1})
    if "b" in parts:
        print("(b) five bites jointly", flush=True)
        out["b_five_bites"] = _pair("five bites 0.6 s", {"kind": "bite", "window_s": 0.6,
                                                         "n": 5})
    if "c" in parts:
        n = 5 if args.quick else args.starts
        print(f"(c) {n} poor initial guesses, a bite and a release (0.3 s)", flush=True)
        rng = np.random.default_rng(2024)
        from ident import load_mill

        ids = load_mill(MILL).element_ids
        starts = [{e: float(np.exp(rng.uniform(np.log(3e-4), np.log(1.5e-2)))) for e in ids}
                  for _ in range(n)]
        res: dict[str, list] = {"shooting": [], "collocation": []}
        for k, st in enumerate(starts):
            for method in res:
                r = _run({"kind": "both", "window_s": 0.3, "n": 2, "method": method,
                          "start": st, "uncertainty": False})
                res[method].append(r)
                print(f"  start {k:2d} {method:<12} {r['wall_s']:6.1f} s  success={r['success']}"
                      f"  {r['status'][:30]}", flush=True)
        out["c_poor_starts"] = {
            m: {"success": sum(r["success"] for r in v), "of": len(v),
                "median_wall_s": float(np.median([r["wall_s"] for r in v])),
                "runs": v} for m, v in res.items()}
        print("  success: " + ", ".join(f"{m} {d['success']}/{d['of']}" for m, d in
                                        out["c_poor_starts"].items()), flush=True)
    if "d" in parts:
        print("(d) one 3 s window with the idle rattle after a release", flush=True)
        out["d_rattle_3s"] = _pair("release + rattle 3 s", {"kind": "release", "window_s": 3.0,
                                                            "n": 1})
    if "scale" in parts:
        print("scaling of collocation (releases)", flush=True)
        rows = []
        for ws, n in ((0.3, 1), (0.6, 1), (1.2, 1), (0.3, 2), (0.3, 4)):
            r = _run({"kind": "release" if n == 1 else "both", "window_s": ws, "n": n,
                      "method": "collocation", "uncertainty": False})
            rows.append(r)
            print(f"  {n} window(s) of {ws} s: {r['samples']} samples, "
                  f"{r['nlp'].get('variables')} variables, {r['iterations']} it, "
                  f"{r['wall_s']} s wall, {r['peak_rss_mb']:.0f} MB", flush=True)
        out["scaling"] = rows
    out["load_average_end"] = os.getloadavg()
    d = ROOT / "benchmarks" / "results"
    d.mkdir(parents=True, exist_ok=True)
    (d / "bench_fit.json").write_text(json.dumps(out, indent=1, default=float) + "\n")
    print(f"bench_fit: load average {out['load_average_end']}; results in "
          f"benchmarks/results/bench_fit.json", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
