"""Refit from neighbours: which recordings a campaign fits again, and from which gaps.

A fit started at the mill file's gaps may not identify a gap that has grown far
from them; started at the gaps a neighbouring recording of the same mill
identified, it often does (``ident fit --start-from``).  After its first pass the
campaign (:func:`ident.store.run_campaign`) refits, in time order, every
recording that left a gap unidentified that some other recording identified,
starting from the nearest such recording.  The choice depends only on the
stored first-pass fits, so a rerun makes the same choices and finds the refits
stored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

__all__ = ["Refit", "neighbour_starts"]


@dataclass(frozen=True)
class Refit:
    """One recording to fit again.

    Attributes
    ----------
    file_name, content_sha256 : str
        The recording.
    neighbour : str
        File name of the recording whose gaps start the fit.
    missing : tuple of str
        Elements the first fit did not identify and the neighbour did.
    starts : tuple of (str, float)
        Start gaps, rad, sorted by element: the neighbour's, with the recording's own
        identified gaps kept.
    """

    file_name: str
    content_sha256: str
    neighbour: str
    missing: tuple[str, ...]
    starts: tuple[tuple[str, float], ...]


def _ok(g: Any) -> bool:
    return isinstance(g, (int, float)) and math.isfinite(g) and g >= 0


def neighbour_starts(fits: Iterable[Mapping[str, Any]]) -> tuple[Refit, ...]:
    """The refits of a campaign's first pass.

    Parameters
    ----------
    fits : iterable of mapping
        Per recording ``file_name``, ``content_sha256``, ``t0_ns`` (ns), ``gaps``
        (``{element: rad}``) and ``identified`` (element ids), as
        :meth:`ident.store.Store.fit_summaries` gives them.

    Returns
    -------
    tuple of Refit
        In ``(t0_ns, file_name)`` order.  A recording is refitted when it left
        unidentified an element that another recording identified; its neighbour
        is the recording that identified most of those elements, the nearest in
        time among them (the earlier one on a tie, then by file name).
    """
    order = sorted(fits, key=lambda d: (d["t0_ns"] or 0, d["file_name"]))
    ever = set().union(*(set(d["identified"]) for d in order)) if order else set()
    out = []
    for r in order:
        missing = ever - set(r["identified"])
        if not missing:
            continue
        t = r["t0_ns"] or 0

        def rank(o: Mapping[str, Any]) -> tuple:
            dt = (o["t0_ns"] or 0) - t
            return (-len(missing & set(o["identified"])), abs(dt), dt > 0, o["file_name"])

        cands = [o for o in order if o is not r and missing & set(o["identified"])]
        if not cands:
            continue
        n = min(cands, key=rank)
        start = {e: float(g) for e, g in n["gaps"].items() if _ok(g)}
        start.update({e: float(g) for e, g in r["gaps"].items()
                      if e in r["identified"] and _ok(g)})
        out.append(Refit(file_name=r["file_name"], content_sha256=r["content_sha256"],
                         neighbour=n["file_name"],
                         missing=tuple(sorted(missing & set(n["identified"]))),
                         starts=tuple(sorted(start.items()))))
    return tuple(out)
