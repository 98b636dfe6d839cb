"""``ident frequencies --mill M``: the linear baseline's natural frequencies and modes."""

from __future__ import annotations

import argparse

from ..model.linear import natural_modes
from .common import add_common, load_mill_arg, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("frequencies", help="natural frequencies and mode shapes (gaps closed)",
                       description="Linear baseline: natural frequencies (Hz) and mode shapes, "
                                   "free-free (gaps closed, speed loop open), rigid-body mode "
                                   "left out.")
    add_common(p)
    p.add_argument("--set", action="append", metavar="ID.KEY=VALUE", help="override a value")


def run(args: argparse.Namespace) -> int:
    mill = load_mill_arg(args)
    lm = natural_modes(mill)
    modes = []
    D_shapes = lm.element_shapes(mill)
    for i, f in enumerate(lm.frequencies_hz):
        modes.append({
            "frequency_hz": float(f),
            "damping_ratio": float(lm.damping_ratios[i]),
            "shape": {mid: float(lm.shapes[j, i]) for j, mid in enumerate(lm.mass_ids)},
            "element_deflection": {e.id: float(D_shapes[j, i])
                                   for j, e in enumerate(mill.elements)},
        })
    write_json({"mill": mill.name, "frequencies_hz": [float(f) for f in lm.frequencies_hz],
                "modes": modes}, args.out)
    return 0
