"""Benchmark: reading an hour of telemetry (MCAP protobuf, MCAP JSON, CSV) against the floors.

Recording (issue 3): 8 torque-like channels at 2 kHz (kN*m) and 4 accelerometer
channels at 10 kHz (g), one hour by default, written block by block (0.1 s blocks)
into a temporary directory as MCAP with protobuf sample blocks, MCAP with JSON
sample blocks, and CSV (one file per device: ``bench.csv`` + ``bench.accel.csv``).

Each read runs in its own child process, so that its peak RSS is its own:

* MCAP floor: ``for _ in make_reader(f).iter_messages(): pass`` (the official reader
  decompressing and framing every message, decoding nothing);
* CSV floor: ``pandas.read_csv(path, engine="pyarrow")`` of each file;
* ours: ``ident.io.read_recording(path)`` to SI float32 DataFrames with the quality
  scans; also with ``channels=`` the torque channels only.

Printed: file sizes, MB/s of file bytes, time ratio ours / floor, peak RSS.
Goal: protobuf MCAP within 3x of the bare loop.

Run:  .venv/bin/python -m benchmarks.bench_ingest [--minutes 60] [--repeat 3] [--dir DIR] [--keep]

Measured (one hour, 2 shared cores under load, three runs; the last one):

==============  =======  ===============  ================  =====  ========
format          size     floor            ours              ratio  peak RSS
==============  =======  ===============  ================  =====  ========
MCAP protobuf   815 MB   5.2 s, 158 MB/s  10.2 s, 80 MB/s   1.97   1.22 GB
MCAP JSON       1695 MB  6.5 s            127 s, 13 MB/s    19.6   1.23 GB
CSV (2 files)   2693 MB  50.8 s (6.2 GB)  43.4 s, 62 MB/s   0.85   1.36 GB
==============  =======  ===============  ================  =====  ========

Protobuf ratio over the three runs: 1.91, 2.25, 1.97.  The result itself is 1.15 GB
(0.81 GB float32 samples + 0.35 GB float64 index); the interpreter ~0.13 GB.  Torque
channels only (``channels=``): 5.9 s, peak 0.40 GB.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

T0_NS = 1_732_252_800_000_000_000
TORQUE = tuple(f"T{i}" for i in range(1, 9))
ACCEL = ("A1_v", "A1_h", "A2_v", "A2_h")
RATE_T, RATE_A = 2000.0, 10000.0
CHUNK_S = 10


def _signals(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Chunk ``k`` (CHUNK_S seconds): torque (8, n) kN*m and accel (4, m) g, float32."""
    nt, na = int(CHUNK_S * RATE_T), int(CHUNK_S * RATE_A)
    tt = k * CHUNK_S + np.arange(nt) / RATE_T
    loaded = (np.floor(tt / 7.0) % 2 == 1).astype(np.float32)  # 7 s bars, 7 s pauses
    base = 300.0 * loaded + 40.0 * np.sin(2 * np.pi * 15.0 * tt).astype(np.float32) * loaded
    torque = (base[None, :] * np.linspace(0.5, 1.0, 8, dtype=np.float32)[:, None]
              + rng.standard_normal((8, nt), dtype=np.float32) * 5.0)
    ta = k * CHUNK_S + np.arange(na) / RATE_A
    amp = 0.05 + 0.3 * np.repeat(loaded, na // nt)
    accel = (amp * np.sin(2 * np.pi * 420.0 * ta)).astype(np.float32)[None, :] \
        + rng.standard_normal((4, na), dtype=np.float32) * 0.02
    return torque.astype(np.float32), accel.astype(np.float32)


def generate(directory: Path, minutes: float) -> dict[str, list[Path]]:
    """Write the three recordings; returns the files of each format."""
    from ident.io.writers import CsvDeviceWriter, McapRecordingWriter, csv_sibling_path

    files = {"mcap-protobuf": [directory / "bench-pb.mcap"],
             "mcap-json": [directory / "bench-json.mcap"],
             "csv": [directory / "bench.csv", csv_sibling_path(directory / "bench.csv",
                                                                "/telemetry/accel")]}
    rng = np.random.default_rng(0)
    n_chunks = max(1, int(round(minutes * 60 / CHUNK_S)))
    mcaps = [McapRecordingWriter(files["mcap-protobuf"][0], encoding="protobuf"),
             McapRecordingWriter(files["mcap-json"][0], encoding="json")]
    ids = [(w.add_device("/telemetry/torque", rate_hz=RATE_T, channels=TORQUE,
                         units=("kN*m",) * 8),
            w.add_device("/telemetry/accel", rate_hz=RATE_A, channels=ACCEL, units=("g",) * 4))
           for w in mcaps]
    csvs = [CsvDeviceWriter(files["csv"][0], channels=TORQUE, units=("kN*m",) * 8,
                            rate_hz=RATE_T, origin_ns=T0_NS),
            CsvDeviceWriter(files["csv"][1], channels=ACCEL, units=("g",) * 4,
                            rate_hz=RATE_A, origin_ns=T0_NS)]
    bt, ba = int(RATE_T / 10), int(RATE_A / 10)
    for k in range(n_chunks):
        torque, accel = _signals(rng, k)
        t_chunk = T0_NS + k * CHUNK_S * 1_000_000_000
        for b in range(CHUNK_S * 10):
            t0 = t_chunk + b * 100_000_000
            for w, (it, ia) in zip(mcaps, ids):
                w.write_block(it, t0, torque[:, b * bt:(b + 1) * bt])
                w.write_block(ia, t0, accel[:, b * ba:(b + 1) * ba])
        csvs[0].write_block(t_chunk, torque)
        csvs[1].write_block(t_chunk, accel)
        if k % 30 == 29:
            print(f"  generated {(k + 1) * CHUNK_S / 60:.0f} of {minutes:g} min", file=sys.stderr)
    for w in mcaps + csvs:
        w.close()
    return files


# ---- measurements (each in a child process) ---------------------------------------------------
def _measure(kind: str, paths: list[str]) -> dict[str, float]:
    import pandas as pd
    from mcap.reader import make_reader

    from ident.io import read_recording

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    if kind == "mcap-floor":
        with open(paths[0], "rb") as fh:
            for _ in make_reader(fh).iter_messages():
                pass
    elif kind == "csv-floor":
        for p in paths:
            df = pd.read_csv(p, engine="pyarrow")
            del df
    elif kind in ("ours", "ours-torque"):
        channels = list(TORQUE) if kind == "ours-torque" else None
        rec = read_recording(paths[0], channels=channels, warn=False)
        assert rec.issues == (), rec.issues
    elif kind == "ours-windows":  # the whole file, one minute at a time (iter_recording)
        from ident.io import iter_recording

        n = 0
        for rec in iter_recording(paths[0], window_s=60.0, warn=False):
            n += sum(len(f) for f in rec.frames.values())
            del rec
    else:
        raise SystemExit(f"unknown measurement {kind!r}")
    seconds = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"seconds": seconds, "peak_rss_mb": peak / 1024.0, "base_rss_mb": rss0 / 1024.0}


def _child(kind: str, paths: list[Path]) -> dict[str, float]:
    out = subprocess.run([sys.executable, "-m", "benchmarks.bench_ingest", "--measure", kind,
                          *map(str, paths)], check=True, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="recording length (default 60)")
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the generated files")
    ap.add_argument("--repeat", type=int, default=3,
                    help="protobuf MCAP floor and ours, interleaved, this many times; the "
                         "median is reported (default 3: the machine is shared)")
    ap.add_argument("--measure", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.measure:
        print(json.dumps(_measure(args.measure[0], args.measure[1:])))
        return
    directory = args.dir or Path(tempfile.mkdtemp(prefix="ident-bench-ingest-"))
    directory.mkdir(parents=True, exist_ok=True)
    try:
        n_values = args.minutes * 60 * (8 * RATE_T + 4 * RATE_A)
        print(f"ingest benchmark: {args.minutes:g} min, 8 ch x 2 kHz + 4 ch x 10 kHz "
              f"({n_values / 1e6:.0f} M samples) in {directory}")
        t = time.perf_counter()
        files = generate(directory, args.minutes)
        print(f"generated in {time.perf_counter() - t:.1f} s")
        # flush the new files (GBs) to disk first: their writeback and the kernel's page
        # reclaim otherwise overlap the first measurements (ours allocates the result,
        # the bare loop does not, so only ours was slowed: 6.3 s vs 2.8 s in one run)
        t = time.perf_counter()
        os.sync()
        print(f"synced in {time.perf_counter() - t:.1f} s")
        rows = []
        for fmt, paths in files.items():
            size_mb = sum(p.stat().st_size for p in paths) / 1e6
            floor_kind = "csv-floor" if fmt == "csv" else "mcap-floor"
            reps = max(1, args.repeat) if fmt == "mcap-protobuf" else 1
            runs = [(_child(floor_kind, paths), _child("ours", paths)) for _ in range(reps)]
            if reps > 1:
                print(f"{fmt}: floor/ours seconds per repeat: " + ", ".join(
                    f"{f['seconds']:.2f}/{o['seconds']:.2f}" for f, o in runs))
            floor = sorted((f for f, _ in runs), key=lambda d: d["seconds"])[reps // 2]
            ours = sorted((o for _, o in runs), key=lambda d: d["seconds"])[reps // 2]
            rows.append((fmt, size_mb, floor_kind, floor, ours))
        torque_only = _child("ours-torque", files["mcap-protobuf"])
        windows = {fmt: _child("ours-windows", files[fmt]) for fmt in ("mcap-protobuf", "csv")}
        print()
        print(f"{'format':<14}{'size MB':>9}{'floor s':>9}{'floor MB/s':>11}{'ours s':>8}"
              f"{'ours MB/s':>10}{'ratio':>7}{'floor RSS':>10}{'ours RSS':>9}")
        for fmt, size_mb, floor_kind, floor, ours in rows:
            print(f"{fmt:<14}{size_mb:>9.0f}{floor['seconds']:>9.1f}"
                  f"{size_mb / floor['seconds']:>11.0f}{ours['seconds']:>8.1f}"
                  f"{size_mb / ours['seconds']:>10.0f}{ours['seconds'] / floor['seconds']:>7.2f}"
                  f"{floor['peak_rss_mb']:>9.0f}M{ours['peak_rss_mb']:>8.0f}M")
        print(f"floors: MCAP = bare loop over make_reader(f).iter_messages(); CSV = "
              f"pandas.read_csv(engine='pyarrow') of each file")
        result_mb = n_values * 4 / 1e6 + args.minutes * 60 * (RATE_T + RATE_A) * 8 / 1e6
        print(f"result size (float32 samples + float64 time index): {result_mb:.0f} MB; "
              f"process baseline after imports ~{rows[0][4]['base_rss_mb']:.0f} MB")
        print(f"torque channels only (channels=...), MCAP protobuf: "
              f"{torque_only['seconds']:.1f} s, peak RSS {torque_only['peak_rss_mb']:.0f} MB")
        for fmt, w in windows.items():
            print(f"whole file in 60 s windows (iter_recording), {fmt}: {w['seconds']:.1f} s, "
                  f"peak RSS {w['peak_rss_mb']:.0f} MB")
        pb = rows[0]
        ratio = pb[4]["seconds"] / pb[3]["seconds"]
        print(f"goal: protobuf MCAP within 3x of the bare loop: {ratio:.2f}x -> "
              f"{'met' if ratio <= 3.0 else 'NOT met'}")
    finally:
        if not args.keep and args.dir is None:
            shutil.rmtree(directory, ignore_errors=True)


if __name__ == "__main__":
    main()
