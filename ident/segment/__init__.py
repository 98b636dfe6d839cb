"""Load-step transients (bites and releases) in a recording: where a fit should look.

:func:`segment_transients` returns frozen :class:`Segment` s of a recording in memory;
:func:`segment_file` those of a file of any length, read window by window; :mod:`.loadshare` gives
the static load fraction of every element and its distance to the rolls.
"""
from .files import FileSegments, segment_file
from .loadshare import distance_to_load, load_fractions
from .transients import Segment, segment_transients

__all__ = ["Segment", "segment_transients", "segment_file", "FileSegments", "load_fractions",
           "distance_to_load"]
