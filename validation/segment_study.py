"""How well the segmenter finds load steps, on recordings it was not written for.

``python -m validation.segment_study --per-mill 20`` draws recordings on both
mills (``hsm-f1``, ``cold-s5``) from four generators, segments each one as
``ident segment`` does (:func:`ident.segment.segment_file`) and scores every load
step against the generator's truth:

* ``plant``: :func:`validation.plantsim.make_recording` (3 bars, first bite
  1.0-2.5 s, every other recording CSV), the independent plant simulator;
* ``plant-early``: :func:`validation.plantsim.draw_plant` with the first bite
  drawn in 0.5-2.0 s and 3-5 bars;
* ``ident``: the project's own simulator as ``ident simulate`` runs it
  (:func:`ident.model.scenario.random_scenario`, :func:`ident.model.simulate`,
  :func:`ident.model.simulate.sensor_devices`; first bite at 0.5 s, bars at
  25-100 % of the nominal torque), gaps drawn 0.5-3 x designed and SNR 30-40 dB;
  the truth is the half height of the noise-free torque nearest the rolls;
* ``synth``: ``tests/synth_telemetry.py`` (hsm-f1 only: its modes are hsm-f1's).

Recording ``k`` of a generator and mill uses seed ``first_seed + k``
(``--first-seed``, default 100: development used seeds 0-9).  A truth step is
*found* when a segment of the same kind has its ``t_step`` within 5 ms (cli.md:
half height of the torque nearest the rolls), *off* when the nearest one is
within 0.25 s but further than 5 ms; a segment that matches no truth step within
0.25 s is a *false* step.  The table gives, per mill and generator: recordings,
steps, found, off, missed, false, median and max |t_step error| (of found and off
steps) and the median and max relative error of ``static_torque``; and per mill
the ``plant`` generators together (the acceptance: >= 98 % found, <= 2 % false).
``--json FILE`` writes one line per truth step and per false step.  Recordings
are written to a temporary directory (``--keep DIR`` keeps them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
MILLS = {"hsm-f1": ROOT / "data/mills/hsm-f1.toml", "cold-s5": ROOT / "data/mills/cold-s5.toml"}
GENERATORS = ("plant", "plant-early", "ident", "synth")
FOUND_S = 0.005
MATCH_S = 0.25


# ---- generators: write a recording, return its truth steps ---------------------------------
def _plant(mill, seed: int, directory: Path) -> tuple[Path, list[dict]]:
    from validation import plantsim

    fmt = "csv" if seed % 2 else "mcap"
    path = directory / f"{mill.name}-plant-{seed}.{fmt}"
    truth = plantsim.make_recording(mill, seed, path, n_bars=3, fmt=fmt)
    return path, [{"kind": s["kind"], "t_step": s["t_step"], "static": s["static_torque"]}
                  for s in truth["steps"]]


def _plant_early(mill, seed: int, directory: Path) -> tuple[Path, list[dict]]:
    from validation import plantsim

    fmt = "csv" if seed % 2 else "mcap"
    path = directory / f"{mill.name}-early-{seed}.{fmt}"
    meta = np.random.default_rng([seed, 7])
    draw = plantsim.draw_plant(mill, np.random.default_rng(seed),
                               first_bite_s=float(meta.uniform(0.5, 2.0)),
                               n_bars=int(meta.integers(3, 6)), accelerometers=False)
    rec = plantsim.simulate_plant(mill, draw)
    plantsim.write_plant(rec, path)
    return path, [{"kind": s["kind"], "t_step": s["t_step"], "static": s["static_torque"]}
                  for s in rec.truth["steps"]]


def _ident(mill, seed: int, directory: Path) -> tuple[Path, list[dict]]:
    from ident.io import write_recording
    from ident.model.dynamics import ModelOptions
    from ident.model.scenario import random_scenario
    from ident.model.simulate import sensor_devices, simulate
    from ident.segment import distance_to_load, load_fractions

    rng = np.random.default_rng(seed)
    over = {}
    for e in mill.elements:
        if e.gap > 0:
            f = math.exp(rng.uniform(math.log(0.5), math.log(3.0)))
            over[f"{e.id}.gap"] = e.gap * f
            over[f"{e.id}.gap_open"] = e.gap_open * f
    plant = mill.with_overrides(over)
    sc = random_scenario(plant, n_bars=int(rng.integers(3, 6)), rng=rng)
    res = simulate(plant, sc, options=ModelOptions(bearings=False))
    path = directory / f"{mill.name}-ident-{seed}.{'csv' if seed % 2 else 'mcap'}"
    write_recording(path, sensor_devices(res, rng=rng, snr_db=float(rng.uniform(30.0, 40.0))))
    # truth: half height of the noise-free total torque estimate nearest the rolls
    frac, dist = load_fractions(mill), distance_to_load(mill)
    chans = [c for c in mill.torque_channels() if abs(frac[c.element]) > 0.05]
    d0 = min(dist[c.element] for c in chans)
    near = [c.element for c in chans if dist[c.element] == d0]
    t = res.time
    est = np.mean([res.outputs[f"tau:{e}"].to_numpy() / frac[e] for e in near], axis=0)

    def level(a: float, b: float) -> float:
        return float(np.median(est[(t >= a) & (t < b)]))

    def half(t_from: float, before: float, after: float) -> float:
        i0 = int(np.searchsorted(t, t_from))
        lvl = 0.5 * (before + after)
        x = est[i0:] - lvl
        hit = np.flatnonzero(x >= 0 if after > before else x <= 0)
        i = i0 + int(hit[0])
        a, b = est[i - 1] - lvl, est[i] - lvl
        return float(t[i - 1] + (a / (a - b) if a != b else 0.0) * (t[i] - t[i - 1]))

    steps = []
    for k, bar in enumerate(sc.bars):
        idle_before = level(bar.t_bite - 0.3, bar.t_bite)
        rolling = level(bar.t_release - 0.5, bar.t_release)
        end = sc.bars[k + 1].t_bite if k + 1 < len(sc.bars) else t[-1]
        idle_after = level(bar.t_release + bar.fall_time + 0.6, min(end, bar.t_release
                                                                     + bar.fall_time + 0.9))
        steps.append({"kind": "bite", "t_step": half(bar.t_bite, idle_before, rolling),
                      "static": bar.static_torque})
        steps.append({"kind": "release", "t_step": half(bar.t_release, rolling, idle_after),
                      "static": bar.static_torque})
    return path, steps


def _synth(mill, seed: int, directory: Path) -> tuple[Path, list[dict]]:
    sys.path.insert(0, str(ROOT / "tests"))
    from synth_telemetry import make_synth

    from ident.io import write_recording

    s = make_synth(mill, seed=seed, duration_s=40.0, with_accel=False)
    path = directory / f"{mill.name}-synth-{seed}.mcap"
    write_recording(path, s.devices)
    return path, [{"kind": tr.kind, "t_step": tr.t_step, "static": tr.static} for tr in s.truth]


# ---- scoring --------------------------------------------------------------------------------
def score(segments, steps: list[dict]) -> tuple[list[dict], list[dict]]:
    """Each truth step's nearest unused segment of its kind; and the segments left over."""
    rows, used = [], set()
    for st in steps:
        cand = [(abs(s.t_step - st["t_step"]), k) for k, s in enumerate(segments)
                if s.kind == st["kind"] and k not in used]
        cand = [c for c in cand if c[0] <= MATCH_S]
        row = {"kind": st["kind"], "t_true": st["t_step"], "static_true": st["static"]}
        if cand:
            _, k = min(cand)
            used.add(k)
            s = segments[k]
            err = s.t_step - st["t_step"]
            row.update(t_found=s.t_step, error_s=err, static=s.static_torque,
                       status="found" if abs(err) <= FOUND_S else "off")
        else:
            row["status"] = "missed"
        rows.append(row)
    false = [{"kind": s.kind, "t_found": s.t_step, "static": s.static_torque, "status": "false"}
             for k, s in enumerate(segments) if k not in used]
    return rows, false


def run_one(job: tuple[str, str, int, str]) -> dict[str, Any]:
    """Generate, segment and score one recording (in a worker process)."""
    gen, mill_name, seed, directory = job
    import ident
    from ident.segment import segment_file

    mill = ident.load_mill(MILLS[mill_name])
    d = Path(directory)
    t0 = time.perf_counter()
    make = {"plant": _plant, "plant-early": _plant_early, "ident": _ident, "synth": _synth}[gen]
    path, steps = make(mill, seed, d)
    t1 = time.perf_counter()
    found = segment_file(path, mill)
    t2 = time.perf_counter()
    rows, false = score(found.segments, steps)
    for r in rows + false:
        r.update(generator=gen, mill=mill_name, seed=seed)
    return {"rows": rows, "false": false, "gen_s": t1 - t0, "segment_s": t2 - t1,
            "generator": gen, "mill": mill_name, "seed": seed}


def summarise(results: list[dict]) -> list[dict]:
    """One summary per (mill, generator), then per mill over the plant generators."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in results:
        groups.setdefault((r["mill"], r["generator"]), []).append(r)
    for mill in MILLS:
        plant = [r for r in results if r["mill"] == mill and r["generator"].startswith("plant")]
        if plant:
            groups[(mill, "plant, all")] = plant
    out = []
    for (mill, gen), rs in groups.items():
        rows = [row for r in rs for row in r["rows"]]
        false = sum(len(r["false"]) for r in rs)
        errs = np.array([abs(row["error_s"]) for row in rows if "error_s" in row]) * 1e3
        rel = np.array([abs(row["static"] / row["static_true"] - 1.0) for row in rows
                        if "static" in row and math.isfinite(row["static"])])
        n = len(rows)
        out.append({"mill": mill, "generator": gen, "recordings": len(rs), "steps": n,
                    "found": sum(row["status"] == "found" for row in rows),
                    "off": sum(row["status"] == "off" for row in rows),
                    "missed": sum(row["status"] == "missed" for row in rows), "false": false,
                    "median_ms": float(np.median(errs)) if errs.size else math.nan,
                    "max_ms": float(np.max(errs)) if errs.size else math.nan,
                    "static_median": float(np.median(rel)) if rel.size else math.nan,
                    "static_max": float(np.max(rel)) if rel.size else math.nan,
                    "segment_s": float(np.mean([r["segment_s"] for r in rs]))})
    order = {g: i for i, g in enumerate(GENERATORS + ("plant, all",))}
    return sorted(out, key=lambda s: (list(MILLS).index(s["mill"]), order[s["generator"]]))


def table(summary: list[dict]) -> str:
    head = (f"{'mill':8} {'generator':12} {'rec':>4} {'steps':>6} {'found':>6} {'%':>6} "
            f"{'off':>4} {'miss':>4} {'false':>5} {'med ms':>7} {'max ms':>7} "
            f"{'static med':>10} {'max':>6} {'seg s':>6}")
    lines = [head, "-" * len(head)]
    for s in summary:
        pct = 100.0 * s["found"] / s["steps"] if s["steps"] else math.nan
        lines.append(f"{s['mill']:8} {s['generator']:12} {s['recordings']:4d} {s['steps']:6d} "
                     f"{s['found']:6d} {pct:6.1f} {s['off']:4d} {s['missed']:4d} "
                     f"{s['false']:5d} {s['median_ms']:7.2f} {s['max_ms']:7.2f} "
                     f"{100 * s['static_median']:9.2f}% {100 * s['static_max']:5.1f}% "
                     f"{s['segment_s']:6.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m validation.segment_study",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-mill", type=int, default=20, metavar="N",
                    help="recordings per mill and generator (default 20)")
    ap.add_argument("--first-seed", type=int, default=100, metavar="S",
                    help="seed of the first recording (default 100; development used 0-9)")
    ap.add_argument("--generators", default=",".join(GENERATORS),
                    help=f"comma-separated subset of {', '.join(GENERATORS)}")
    ap.add_argument("--mills", default=",".join(MILLS), help="comma-separated subset of "
                    f"{', '.join(MILLS)}")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--json", metavar="FILE", help="write one line per step and false step")
    ap.add_argument("--keep", metavar="DIR", help="write the recordings here and keep them")
    args = ap.parse_args(argv)
    gens = [g for g in args.generators.split(",") if g]
    mills = [m for m in args.mills.split(",") if m]
    bad = [g for g in gens if g not in GENERATORS] + [m for m in mills if m not in MILLS]
    if bad or args.per_mill < 1:
        ap.error(f"unknown generator or mill {bad}" if bad else "--per-mill must be >= 1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    tmp = None
    if args.keep:
        directory = Path(args.keep)
        directory.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="segment_study-")
        directory = Path(tmp.name)
    jobs = [(g, m, args.first_seed + k, str(directory)) for m in mills for g in gens
            if not (g == "synth" and m != "hsm-f1") for k in range(args.per_mill)]
    results = []
    t0 = time.perf_counter()
    try:
        if args.jobs > 1:
            with ProcessPoolExecutor(args.jobs) as ex:
                for r in ex.map(run_one, jobs):
                    results.append(r)
                    _progress(r, len(results), len(jobs))
        else:
            for job in jobs:
                results.append(run_one(job))
                _progress(results[-1], len(results), len(jobs))
    finally:
        if tmp is not None:
            tmp.cleanup()
    summary = summarise(results)
    print(f"segment study: seeds {args.first_seed}-{args.first_seed + args.per_mill - 1}, "
          f"{len(jobs)} recordings, {time.perf_counter() - t0:.0f} s")
    print(table(summary))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            for r in results:
                for row in r["rows"] + r["false"]:
                    fh.write(json.dumps(row) + "\n")
    return 0


def _progress(r: dict, done: int, total: int) -> None:
    bad = [row for row in r["rows"] if row["status"] != "found"] + r["false"]
    note = "; ".join(f"{b['status']} {b['kind']} at "
                     f"{b.get('t_true', b.get('t_found')):.3f} s" for b in bad)
    print(f"[{done}/{total}] {r['generator']} {r['mill']} seed {r['seed']}: "
          f"{len(r['rows'])} steps{', ' + note if note else ''} "
          f"({r['gen_s']:.1f} + {r['segment_s']:.2f} s)", file=sys.stderr, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
