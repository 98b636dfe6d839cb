"""One device's samples on a uniform time grid, as the format readers hand them over.

Internal to :mod:`ident.io`: the MCAP and CSV readers fill a :class:`DeviceGrid`
each; :func:`ident.io.readers.read_recording` checks units, scans quality, converts
to SI in place and wraps the arrays in DataFrames without copying.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass, field

import numpy as np

__all__ = ["DeviceGrid", "empty_buffer"]

#: Buffers from this size on are anonymous memory maps (see :func:`empty_buffer`).
MMAP_MIN_BYTES = 1 << 24


def empty_buffer(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """An uninitialised, writable array for a large sample buffer.

    From 16 MB on, the memory is an anonymous ``mmap`` rather than NumPy's allocator.
    On Linux NumPy marks large allocations ``MADV_HUGEPAGE``; with the common
    ``transparent_hugepage/defrag = madvise`` setting, faulting such pages in can stall
    on synchronous compaction (numpy/numpy#31590).  On this machine, first-touching
    1.2 GB took 3.1 s that way against 0.7-1.2 s with plain pages, and it was most of
    the time of reading an hour of telemetry.  The map is released with the array (its
    base).  This is local to the buffer: NumPy's global setting is left alone.
    """
    dt = np.dtype(dtype)
    n = int(np.prod(shape, dtype=np.int64)) if len(shape) else 1
    nbytes = n * dt.itemsize
    if nbytes < MMAP_MIN_BYTES:
        return np.empty(shape, dtype=dt)
    return np.frombuffer(mmap.mmap(-1, nbytes), dtype=dt, count=n).reshape(shape)


@dataclass
class DeviceGrid:
    """Samples of one device on the grid ``start_ns + k / rate_hz``.

    Attributes
    ----------
    name : str
        Device name (MCAP topic, or the CSV file's device tag).
    rate_hz : float
    start_ns : int
        Time of sample 0, ns (since the Unix epoch, or since an unknown origin for
        CSV files with relative float seconds).
    channels, units : tuple of str
        The channels kept and their recorded units (``""`` when the file gives none).
    data : ndarray, shape (n_channels, n), float32
        Recorded values, NaN where missing; converted to SI in place later.
    gaps : list of (int, int)
        Dropouts as sample index ranges ``[i0, i1)``.
    all_channels : tuple of str
        Every channel the device records, kept or not.
    time_buffer : ndarray of float64, optional
        A scratch array of length n the index may be written into.
    corrupt_ns : list of (int, int)
        Time ranges (ns, same origin as ``start_ns``) lost to corrupt data and
        already reported, so their gaps are not reported again as dropouts.
    origin_ns : int, optional
        The device's first sample in the whole file (same origin as ``start_ns``)
        when only a time window of it was read; None when all of it was.
    """

    name: str
    rate_hz: float
    start_ns: int
    channels: tuple[str, ...]
    units: tuple[str, ...]
    data: np.ndarray
    gaps: list[tuple[int, int]] = field(default_factory=list)
    all_channels: tuple[str, ...] = ()
    time_buffer: np.ndarray | None = None
    corrupt_ns: list[tuple[int, int]] = field(default_factory=list)
    origin_ns: int | None = None

    @property
    def n_samples(self) -> int:
        return int(self.data.shape[1])
