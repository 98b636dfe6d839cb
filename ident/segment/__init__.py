"""Load-step transients (bites and releases) in a recording: where a fit should look.

:func:`segment_transients` returns frozen :class:`Segment` s; :mod:`.loadshare` gives
the static load fraction of every element and its distance to the rolls.
"""
from .loadshare import distance_to_load, load_fractions
from .transients import Segment, segment_transients

__all__ = ["Segment", "segment_transients", "load_fractions", "distance_to_load"]
