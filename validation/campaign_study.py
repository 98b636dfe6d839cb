"""A wear campaign from the independent generator, through ``ident campaign`` and ``report --json``.

``make validate-campaign`` (``python -m validation.campaign_study``) writes a
campaign of plant recordings (:mod:`validation.plantsim`, never
``ident.model.simulate``) of one mill: ``--n`` recordings ``--every`` days
apart, one element's gap growing linearly through both of its limits (default
the lower spindle C46 of ``hsm-f1``, 2 -> 10 mrad against 4 and 8 mrad) and
one bearing's radial clearance through its worn limit (B45, 0.3 -> 1.3 mm
against 1.0 mm), every other gap and clearance at its designed value, and one
malformed file (a truncated MCAP).  Each recording's other parameters (load,
ramps, recorder chain, noise, drift) are drawn from its seed.

It runs the campaign as a user would (:func:`ident.store.run_campaign`:
workers, the mill's wear model trained on first use, the refit pass), writes
the report and its status JSON dated the day after the last recording, runs the
campaign again (a resume must do nothing) and checks, printing each figure:

* the growing element ``critical`` and the bearing ``worn`` at the last
  recording, every other measured element ``good``;
* the predicted ``critical_at`` (and ``worn_at``) interval of the growing
  element containing the true crossing date (the linear growth's);
* the malformed file stored as failed with its reason;
* the resume processing nothing.

Exit status 0 when every check holds, 1 otherwise.  Outputs go to
``out/validate/campaign`` (the recordings, ``results.db``, ``report.html``,
``status.json``); ``--fresh`` starts over.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DAY_NS = 86_400 * 10**9
T0_NS = 1_767_225_600_000_000_000  # 2026-01-01 00:00 UTC


def truth_line(n: int, every: float, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Days and values of a linear growth from ``lo`` to ``hi`` over ``n`` recordings."""
    days = every * np.arange(n)
    return days, lo + (hi - lo) * days / max(days[-1], 1e-9)


def crossing_day(days: np.ndarray, values: np.ndarray, limit: float) -> float:
    """Day at which the linear growth reaches ``limit``."""
    slope = (values[-1] - values[0]) / (days[-1] - days[0])
    return float(days[0] + (limit - values[0]) / slope)


def write_campaign(mill, folder: Path, *, n: int, every: float, element: str,
                   gap: tuple[float, float], bearing: str, clearance: tuple[float, float],
                   seed: int) -> dict:
    """The recordings (and one malformed file) under ``folder``; returns the truth."""
    from validation import plantsim

    days, gaps = truth_line(n, every, *gap)
    _, cls = truth_line(n, every, *clearance)
    truth = {"days": days.tolist(), "gap": gaps.tolist(), "clearance": cls.tolist()}
    for i in range(n):
        path = folder / f"day{int(days[i]):02d}" / f"{mill.name}_{i:03d}.mcap"
        if path.is_file():
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng(seed + i)
        draw = plantsim.draw_plant(mill, rng, gaps={element: float(gaps[i])},
                                   clearances={b.id: (float(cls[i]) if b.id == bearing
                                                      else b.clearance)
                                               for b in mill.bearings}, n_bars=2)
        draw = dataclasses.replace(draw, t0_ns=int(T0_NS + days[i] * DAY_NS + 8 * 3600e9))
        plantsim.write_plant(plantsim.simulate_plant(mill, draw), path)
    bad = folder / "incoming" / "truncated.mcap"
    bad.parent.mkdir(parents=True, exist_ok=True)
    first = next(folder.glob("day00/*.mcap"))
    bad.write_bytes(first.read_bytes()[:4096])
    return truth


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m validation.campaign_study",
                                description=__doc__.split("\n")[0])
    p.add_argument("--mill", default="hsm-f1")
    p.add_argument("--n", type=int, default=12, help="recordings (default 12)")
    p.add_argument("--every", type=float, default=3.0, help="days between recordings")
    p.add_argument("--element", default="C46")
    p.add_argument("--gap", type=float, nargs=2, default=(0.002, 0.010), metavar=("FROM", "TO"),
                   help="its gap, rad (reduced)")
    p.add_argument("--bearing", default="B45")
    p.add_argument("--clearance", type=float, nargs=2, default=(3e-4, 1.3e-3),
                   metavar=("FROM", "TO"), help="its radial clearance, m")
    p.add_argument("--seed", type=int, default=4000)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", default="out/validate/campaign")
    p.add_argument("--fresh", action="store_true", help="delete earlier outputs first")
    a = p.parse_args(argv)

    import ident
    from ident.report import build_report
    from ident.store import run_campaign

    out = Path(a.out)
    if a.fresh and out.exists():
        shutil.rmtree(out)
    folder = out / "recordings"
    mill = ident.load_mill(ROOT / "data" / "mills" / f"{a.mill}.toml")
    el = mill.element(a.element)
    br = next(b for b in mill.bearings if b.id == a.bearing)
    t = time.perf_counter()
    truth = write_campaign(mill, folder, n=a.n, every=a.every, element=a.element,
                           gap=tuple(a.gap), bearing=a.bearing,
                           clearance=tuple(a.clearance), seed=a.seed)
    print(f"campaign: {a.n} recordings of {mill.name} every {a.every:g} days, {a.element} "
          f"{a.gap[0] * 1e3:g} -> {a.gap[1] * 1e3:g} mrad (worn {el.gap_worn * 1e3:g}, critical "
          f"{el.gap_critical * 1e3:g}), {a.bearing} {a.clearance[0] * 1e3:g} -> "
          f"{a.clearance[1] * 1e3:g} mm (worn {br.clearance_worn * 1e3:g}); written in "
          f"{time.perf_counter() - t:.0f} s", flush=True)
    url = f"sqlite:///{out.resolve()}/results.db"
    t = time.perf_counter()
    s = run_campaign(folder, mill, url, workers=a.workers, train=True, progress=True)
    wall = time.perf_counter() - t
    print(f"campaign: {s.n_done} done, {s.n_failed} failed, {s.n_refit} refitted in "
          f"{wall:.0f} s ({s.throughput_per_min:.2f}/min)", flush=True)
    t_last = T0_NS + truth["days"][-1] * DAY_NS
    now = dt.datetime.fromtimestamp(t_last / 1e9 + 86400, tz=dt.timezone.utc)
    rep = build_report(url, out / "report.html", mill=mill, now=now, json_out=out / "status.json")
    doc = json.loads((out / "status.json").read_text())["mills"][mill.name]
    s2 = run_campaign(folder, mill, url, workers=a.workers, progress=False)

    checks: list[tuple[str, bool, str]] = []
    parts = doc["elements"]
    measured = {c.element for c in mill.torque_channels()}
    for eid, d in sorted(parts.items()):
        want = "critical" if eid == a.element else ("good" if eid in measured else None)
        if want is None:
            print(f"  {eid}: {d['status']} (no torque channel: not judged)")
            continue
        checks.append((f"{eid} {want}", d["status"] == want,
                       f"{d['status']} now {d['now']} ({d['n_identified']}/{d['n_recordings']} "
                       f"identified, source {d['source']})"))
    d = doc["bearings"].get(a.bearing, {})
    checks.append((f"{a.bearing} worn", d.get("status") == "worn",
                   f"{d.get('status')} now {d.get('now')} source {d.get('source')}"))
    g = parts.get(a.element, {})
    for name, limit in (("worn", el.gap_worn), ("critical", el.gap_critical)):
        day = crossing_day(np.array(truth["days"]), np.array(truth["gap"]), limit)
        true_date = dt.datetime.fromtimestamp(T0_NS / 1e9 + day * 86400 + 8 * 3600,
                                              tz=dt.timezone.utc).date().isoformat()
        ci = g.get(f"{name}_at_ci95")
        ok = bool(ci) and ci[0] <= true_date <= ci[1]
        checks.append((f"{a.element} {name}_at interval holds {true_date}", ok,
                       f"at {g.get(f'{name}_at')} ci95 {ci}"))
    failed = dict(s.failed)
    checks.append(("malformed file stored as failed", "incoming/truncated.mcap" in failed,
                   failed.get("incoming/truncated.mcap", "not failed")[:100]))
    checks.append(("resume does nothing", s2.n_done == 0 and s2.n_skipped == s.n_found,
                   f"done {s2.n_done}, skipped {s2.n_skipped} of {s2.n_found}"))
    print(f"report: {rep.path}, status {out / 'status.json'}")
    for name, ok, what in checks:
        print(f"  [{'ok' if ok else 'MISS'}] {name}: {what}")
    n_ok = sum(ok for _, ok, _ in checks)
    print(f"campaign study: {n_ok}/{len(checks)} checks hold")
    return 0 if n_ok == len(checks) else 1


if __name__ == "__main__":
    sys.exit(main())
