"""Scorecard of the discrepancy workflow on recordings with hidden effects.

For every effect of effects.md and the two controls (nothing missing, a
sensor-chain filter outside the library), ``--draws`` recordings are simulated
with the effect at a location and strength drawn from a seed
(:func:`ident.discrepancy.hidden_effect_case`); the workflow answers each, and
the scorecard counts right / wrong / null names and the held-out nrmse before
and after.  One JSON line per case goes to ``--out`` (appended; cases already
there are skipped, so the run resumes), a table to stdout.

    .venv/bin/python benchmarks/bench_discrepancy.py --draws 3 --out bench_discrepancy.jsonl

Runtime: about 16-30 s CPU per case (4 bars; wall time more on a shared machine).

Measured (``--draws 5``, seeds 1000-1004, 4 bars, 2 shared cores under load):

====================  =====  =====  =====  ======  =======  ================
effect                right  wrong  null   before  after    shrink (named)
====================  =====  =====  =====  ======  =======  ================
backlash              5      0      0      0.086   0.035    0.57
softening_stiffness   5      0      0      0.224   0.036    0.78
hardening_stiffness   4      0      1      0.157   0.041    0.69
spindle_imbalance     1      0      4      0.075   0.068    0.33
coulomb_friction      4      0      1      0.076   0.037    0.55
strip_coupling        5      0      0      0.161   0.033    0.80
torque_loop_lag       5      0      0      0.244   0.042    0.82
none (control)        5      0      --     0.033   0.033    (best <= 4 %)
sensor_filter         5      0      --     0.157   0.157    (best <= 3.7 %)
====================  =====  =====  =====  ======  =======  ================

The same seeds with 3 bars and the earlier workflow (two folds, one of them
training on a single bar; idle runs with the windows' kink rounding; bites
after a release forced to start from the simulated idle) named no imbalance
(0/0/5) and friction 3/0/2.  What is left: the missed friction sits in the
gearbox mesh C23, which no torque channel sees, and even at the true
parameters lowers the held-out nrmse by only about 30 % (its before is close
to the 0.03 noise floor); the imbalance shows in the bites through the idle
rattle before them, which a model run through one or two seconds of idling
reproduces only sometimes (a few impacts: small errors in the gaps or the
phase move every later one), so its held-out gain ranges from 0 to about 50 %
with the true parameters.  The hardening miss is the location rule: the
signatures scored C23 and C12 alike.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from ident import load_mill
from ident.discrepancy import CONTROLS, discrepancy, hidden_effect_case
from ident.model.effects import EFFECT_NAMES

ROOT = Path(__file__).resolve().parents[1]


def run_case(mill, effect: str, seed: int, n_bars: int) -> dict:
    case = hidden_effect_case(mill, effect, seed=seed, n_bars=n_bars)
    t, cpu = time.perf_counter(), time.process_time()
    res = discrepancy(case.recording, case.mill)
    exp_effect, exp_loc = case.expected
    if res.effect is None:
        verdict = "null"
    elif (res.effect, res.location) == (exp_effect, exp_loc):
        verdict = "right"
    else:
        verdict = "wrong"
    if exp_effect is None:
        verdict = "right" if res.effect is None else "wrong"
    best = res.refits[0] if res.refits else None
    return {"effect": effect, "seed": seed, "location": case.location,
            "params": dict(case.params), "answer": res.effect, "answer_location": res.location,
            "verdict": verdict, "before": res.before, "after": res.after,
            "shrink": 1.0 - res.after / res.before,
            "best": best.key if best else None,
            "best_improvement": best.improvement if best else None,
            "best_folds": list(best.fold_improvements) if best else None,
            "refits": [[r.key, r.improvement, list(r.fold_improvements), r.delta_bic]
                       for r in res.refits],
            "top_scores": [[c.key, c.score] for c in res.candidates[:5]],
            "reason": res.reason, "seconds": time.perf_counter() - t,
            "cpu_seconds": time.process_time() - cpu}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--bars", type=int, default=4)
    ap.add_argument("--effects", nargs="*", default=list(EFFECT_NAMES) + list(CONTROLS))
    ap.add_argument("--out", default="bench_discrepancy.jsonl")
    ap.add_argument("--mill", default=str(ROOT / "data" / "mills" / "hsm-f1.toml"))
    args = ap.parse_args(argv)
    mill = load_mill(args.mill)
    out = Path(args.out)
    done = set()
    rows = []
    if out.exists():
        for line in out.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                rows.append(r)
                done.add((r["effect"], r["seed"]))
    for d in range(args.draws):
        for effect in args.effects:
            seed = args.first_seed + d
            if (effect, seed) in done:
                continue
            r = run_case(mill, effect, seed, args.bars)
            rows.append(r)
            with out.open("a") as fh:
                fh.write(json.dumps(r) + "\n")
            print(f"{effect:22s} seed {seed}: {r['verdict']:5s} answer {r['answer']}@"
                  f"{r['answer_location']} (truth @{r['location']}), nrmse {r['before']:.4f} -> "
                  f"{r['after']:.4f}, best {r['best']} {r['best_improvement']}, "
                  f"{r['seconds']:.0f} s ({r['cpu_seconds']:.0f} s CPU)", flush=True)
    print(scorecard(rows))
    return 0


def scorecard(rows: list[dict]) -> str:
    """Per effect: right / wrong / null counts and mean held-out nrmse before -> after."""
    lines = [f"{'effect':22s} {'n':>3s} {'right':>5s} {'wrong':>5s} {'null':>5s} "
             f"{'before':>7s} {'after':>7s} {'shrink(named)':>13s} {'cpu_s':>6s}"]
    for effect in dict.fromkeys(r["effect"] for r in rows):
        rs = [r for r in rows if r["effect"] == effect]
        named = [r for r in rs if r["answer"] is not None]
        shrink = (sum(r["shrink"] for r in named) / len(named)) if named else float("nan")
        lines.append(f"{effect:22s} {len(rs):3d} {sum(r['verdict'] == 'right' for r in rs):5d} "
                     f"{sum(r['verdict'] == 'wrong' for r in rs):5d} "
                     f"{sum(r['answer'] is None for r in rs):5d} "
                     f"{sum(r['before'] for r in rs) / len(rs):7.4f} "
                     f"{sum(r['after'] for r in rs) / len(rs):7.4f} {shrink:13.2f} "
                     f"{sum(r.get('cpu_seconds', math.nan) for r in rs) / len(rs):6.1f}")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
