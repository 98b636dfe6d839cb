"""Options and output shared by the subcommands."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from ..description import Mill
from ..errors import MillFileError
from ..io.millfile import load_mill
from ..io.channels import require_channels
from ..io.writers import AtomicFile

__all__ = ["add_common", "load_mill_arg", "write_json", "to_jsonable", "parse_sets",
           "require_channels"]


def add_common(p: argparse.ArgumentParser, *, out: bool = True, out_required: bool = False,
               out_help: str = "write the JSON here instead of stdout") -> None:
    """Add ``--mill``, ``--out`` and ``--quiet`` to a subcommand."""
    p.add_argument("--mill", required=True, metavar="FILE", help="mill description (TOML)")
    if out:
        p.add_argument("--out", metavar="FILE", required=out_required, help=out_help)
    p.add_argument("--quiet", action="store_true", help="no progress output on stderr")


def load_mill_arg(args: argparse.Namespace) -> Mill:
    """Load ``--mill`` and apply any ``--set ID.KEY=VALUE`` overrides.

    Raises
    ------
    MillFileError
        The mill file is bad (naming the file), or an override is (naming ``--set``,
        the key and the value: the file itself was valid).
    """
    mill = load_mill(args.mill)
    sets = getattr(args, "set", None)
    if sets:
        overrides = parse_sets(sets)
        try:
            mill = mill.with_overrides(overrides)
        except MillFileError as exc:
            raise _set_error(exc, sets) from None
    return mill


def _set_error(exc: MillFileError, items: list[str]) -> MillFileError:
    """The error of an override, naming the ``--set`` option(s) that caused it."""
    key = exc.key or ""
    own = [s for s in items if s.split("=", 1)[0].strip() == key]  # unknown id or key
    if not own and "." in key:  # revalidation: 'element[C46].gap' <- --set C46.gap=...
        table_id, _, name = key.rpartition(".")
        ident = table_id[table_id.find("[") + 1:-1] if table_id.endswith("]") else table_id
        own = [s for s in items if s.split("=", 1)[0].strip() == f"{ident}.{name}"] or \
            [s for s in items if s.split(".", 1)[0].strip() == ident]
    shown = " ".join(f"--set {s}" for s in (own or items))
    same = any(s.split("=", 1)[0].strip() == key for s in own)
    err = MillFileError(f"{shown}: {exc.reason}" if same or not key else
                        f"{shown}: {key}: {exc.reason}")
    err.key = key or None  # kept for callers; the message names --set, not the mill file
    return err


def parse_sets(items: list[str]) -> dict[str, Any]:
    """Parse ``ID.KEY=VALUE`` strings; values are numbers where they parse as such."""
    out: dict[str, Any] = {}
    for item in items:
        k, eq, v = item.partition("=")
        if not eq or "." not in k or not k.split(".", 1)[1].strip():
            err = MillFileError(f"--set {item}: expected ID.KEY=VALUE, e.g. C46.gap=0.006")
            err.key = k.strip() or None
            raise err
        try:
            val: Any = float(v)
        except ValueError:
            val = v.strip()
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
    f = AtomicFile(out, "w")  # honours the umask (mkstemp alone gives 0600)
    try:
        f.fh.write(text + "\n")
        f.commit()
    except BaseException:
        f.abort()
        raise
