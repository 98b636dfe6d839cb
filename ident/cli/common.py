"""Options and output shared by the subcommands."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..description import Mill
from ..errors import IdentError, MillFileError
from ..io.millfile import load_mill

__all__ = ["add_common", "load_mill_arg", "write_json", "to_jsonable", "parse_sets"]


def add_common(p: argparse.ArgumentParser, *, out: bool = True, out_required: bool = False,
               out_help: str = "write the JSON here instead of stdout") -> None:
    """Add ``--mill``, ``--out`` and ``--quiet`` to a subcommand."""
    p.add_argument("--mill", required=True, metavar="FILE", help="mill description (TOML)")
    if out:
        p.add_argument("--out", metavar="FILE", required=out_required, help=out_help)
    p.add_argument("--quiet", action="store_true", help="no progress output on stderr")


def load_mill_arg(args: argparse.Namespace) -> Mill:
    """Load ``--mill`` and apply any ``--set ID.KEY=VALUE`` overrides."""
    mill = load_mill(args.mill)
    sets = getattr(args, "set", None)
    if sets:
        mill = mill.with_overrides(parse_sets(sets))
    return mill


def parse_sets(items: list[str]) -> dict[str, Any]:
    """Parse ``ID.KEY=VALUE`` strings; values are numbers where they parse as such."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise MillFileError(f"--set expects ID.KEY=VALUE. Got {item!r}", key=item)
        k, v = item.split("=", 1)
        try:
            val: Any = float(v)
        except ValueError:
            val = v
        out[k.strip()] = val
    return out


def to_jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and non-finite floats for ``json.dumps``."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(data: Any, out: str | None) -> None:
    """Write JSON to ``out`` atomically, or to stdout when ``out`` is None."""
    text = json.dumps(to_jsonable(data), indent=2)
    if out is None:
        sys.stdout.write(text + "\n")
        return
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text + "\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
