"""Which mapped channels each stage needs, and the refusal of a recording that lacks one.

The reader only notes a mapped channel that a recording lacks (``segment`` goes on
without it); the fit, the discrepancy workflow and the diagnosis need theirs, and
:func:`require_channels` says which channel of which file is missing and what for.
Used by the commands (:mod:`ident.cli`) and by the campaign (:mod:`ident.store`).
"""

from __future__ import annotations

from typing import Iterable

from ..description import Mill
from ..errors import RecordingError
from .recording import Recording

__all__ = ["require_channels"]


#: What each command needs a mapped channel for, by quantity: "... needs it {purpose}".
_NEEDS = {
    "fit": {"torque": "to compare the model's torque at element {id} with the measured one"},
    "discrepancy": {"torque": "to compare model and measured torque at element {id}"},
    "diagnose": {"torque": "for the natural-frequency amplitudes and phases at element {id}",
                 "acceleration": "for the wear state of bearing {id}"},
}


def require_channels(rec: Recording, mill: Mill, command: str, *,
                     bearings: Iterable[str] | None = None) -> None:
    """Refuse a recording that lacks a mapped channel ``command`` needs.

    ``fit`` and ``discrepancy`` need every torque channel of the mill file (the model's
    torque at each measured element is compared with it); ``diagnose`` needs those and
    the accelerometers of ``bearings`` (default: every bearing of the mill file).  The
    reader only notes such a channel as missing (``segment`` goes on without it).

    Raises
    ------
    RecordingError
        Naming the file, the (first) missing channel and what the command needs it for.
    """
    needs = _NEEDS[command]
    wanted = None if bearings is None else set(bearings)
    present = set(rec.channels)
    missing = []
    for ch in mill.channels:
        q = ch.quantity.value
        if q not in needs or ch.name in present:
            continue
        ref = ch.element if q == "torque" else ch.bearing
        if q == "acceleration" and wanted is not None and ref not in wanted:
            continue
        missing.append((ch, ref))
    if not missing:
        return
    ch, ref = missing[0]
    where = "element" if ch.quantity.value == "torque" else "bearing"
    more = (f" (nor {', '.join(repr(c.name) for c, _ in missing[1:])})" if len(missing) > 1
            else "")
    raise RecordingError(
        f"missing channel: the mill file maps {ch.quantity.value} channel '{ch.name}' "
        f"({where} {ref}) but the recording lacks it{more}; 'ident {command}' needs it "
        f"{needs[ch.quantity.value].format(id=ref)}", path=rec.path, channel=ch.name)
