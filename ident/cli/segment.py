"""``ident segment REC --mill M``: the load-step transients found in a recording.

Prints (or writes to ``--out``) ``{"segments": [...]}`` with the cli.md keys
``t_start, t_step, t_end, kind, static_torque, step`` per segment (plus
``channel`` and ``rise_s``), and beside it ``recording``, ``mill``, ``channels``
and ``warnings`` (the quality findings of the read, as dicts).
"""

from __future__ import annotations

import argparse
import sys

from ..io.readers import read_recording
from ..segment import segment_transients
from .common import add_common, load_mill_arg, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("segment", help="load-step transients (bites, releases) in a recording",
                       description="Find every bite and release in a recording (MCAP or CSV) "
                                   "and the window a fit should use for each.")
    p.add_argument("recording", metavar="REC", help="recording (.mcap or .csv)")
    add_common(p)


def run(args: argparse.Namespace) -> int:
    mill = load_mill_arg(args)
    rec = read_recording(args.recording, mill, warn=False)  # findings go into the JSON
    segments = segment_transients(rec, mill)
    if not args.quiet:
        print(f"ident segment: {len(segments)} transients, {len(rec.issues)} quality findings",
              file=sys.stderr)
        for issue in rec.issues:
            print(f"ident segment: warning: {issue}", file=sys.stderr)
    write_json({"recording": str(args.recording), "mill": mill.name,
                "channels": list(rec.channels),
                "segments": [s.to_dict() for s in segments],
                "warnings": [i.to_dict() for i in rec.issues]}, args.out)
    return 0
