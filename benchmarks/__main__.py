"""Run every benchmark in turn: ``python -m benchmarks``."""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

if __name__ == "__main__":
    here = Path(__file__).parent
    names = sorted(m.name for m in pkgutil.iter_modules([str(here)]) if m.name.startswith("bench_"))
    for name in names:
        print(f"\n=== benchmarks.{name} ===", flush=True)
        mod = importlib.import_module(f"benchmarks.{name}")
        try:
            mod.main([])
        except SystemExit as exc:  # a benchmark's argparse exit
            if exc.code not in (0, None):
                print(f"benchmarks.{name} exited {exc.code}", file=sys.stderr)
