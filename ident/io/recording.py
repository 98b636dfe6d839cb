"""In-memory recordings: raw device blocks (as written) and SI frames (as read).

A recording holds one or more *devices* (the strain telemetry, the
accelerometer conditioner), each with its own sample rate.  Two views:

* :class:`RawDevice` -- what a file stores: values in the recorded unit
  (``units``), NaN for missing samples.  Writers take these.
* :class:`Recording` -- what readers return: per device a pandas DataFrame of
  SI physical values, indexed by time in seconds from the recording's start
  (``time_s``), plus quality findings that travel with the data.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
import pandas as pd

__all__ = ["RawDevice", "QualityIssue", "Recording"]


@dataclass(frozen=True)
class RawDevice:
    """Samples of one device as a file stores them.

    Attributes
    ----------
    name : str
        Device / MCAP topic name, e.g. ``/telemetry/torque``.
    rate_hz : float
        Sample rate, Hz.
    t0_ns : int
        Time of the first sample, ns since the Unix epoch.
    channels : tuple of str
        Channel names as in the mill file's sensor map.
    units : tuple of str
        Recorded unit per channel (``raw`` where scale/offset apply).
    data : ndarray, shape (n_channels, n_samples)
        Values in ``units``; NaN marks a missing sample.
    """

    name: str
    rate_hz: float
    t0_ns: int
    channels: tuple[str, ...]
    units: tuple[str, ...]
    data: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.data.shape[1])


@dataclass(frozen=True)
class QualityIssue:
    """One data-quality finding.

    Attributes
    ----------
    kind : str
        ``dropout``, ``nan_run``, ``clipped``, ``non_monotonic``, ``rate_mismatch``,
        ``unknown_channel``, ``missing_channel``, ``unit_mismatch``, ``truncated``, ...
    path : str or None
    channel : str or None
    t_start, t_end : float or None
        Seconds from the recording's start.
    message : str
    fatal : bool
    device : str or None
        The device (MCAP topic, CSV file) concerned; ``channel`` then lists its
        channels comma-separated for device-wide findings such as dropouts.

    See :mod:`ident.io.quality` for the kinds and which of them are fatal.
    """

    kind: str
    message: str
    path: str | None = None
    channel: str | None = None
    t_start: float | None = None
    t_end: float | None = None
    fatal: bool = False
    device: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "message": self.message, "path": self.path,
                "channel": self.channel, "t_start": self.t_start, "t_end": self.t_end,
                "fatal": self.fatal, "device": self.device}

    def __str__(self) -> str:
        where = [w for w in (self.path, f"channel '{self.channel}'" if self.channel else None,
                             f"t={self.t_start:.4f} s" if self.t_start is not None else None)
                 if w]
        return f"{', '.join(where)}: {self.kind}: {self.message}"


@dataclass(frozen=True)
class Recording:
    """A recording read into SI, one DataFrame per device.

    Attributes
    ----------
    frames : mapping of str to DataFrame
        Per device: index ``time_s`` (float seconds from the recording start,
        the earliest first sample over all devices), one column per channel in SI
        physical units (torque N*m on the physical shaft, acceleration m/s^2,
        speed rad/s).
    rates_hz : mapping of str to float
        Sample rate per device.
    t0_ns : int
        Absolute start, ns since the Unix epoch.
    path : str or None
    metadata : mapping
        MCAP ``ident.recording`` metadata (``mill``, ``stand``, ``campaign``,
        ``recording_id``) where present.
    mill_toml : str or None
        An attached ``mill.toml``.
    issues : tuple of QualityIssue
        Non-fatal findings, carried into every later result.
    """

    frames: Mapping[str, pd.DataFrame]
    rates_hz: Mapping[str, float]
    t0_ns: int = 0
    path: str | None = None
    metadata: Mapping[str, str] = field(default_factory=dict)
    mill_toml: str | None = None
    issues: tuple[QualityIssue, ...] = ()

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(c for f in self.frames.values() for c in f.columns)

    def device_of(self, channel: str) -> str:
        """Device holding ``channel``; KeyError if none does."""
        for dev, f in self.frames.items():
            if channel in f.columns:
                return dev
        raise KeyError(channel)

    def channel(self, name: str) -> pd.Series:
        """One channel's SI samples as a Series indexed by ``time_s``."""
        return self.frames[self.device_of(name)][name]

    @property
    def duration(self) -> float:
        """Seconds from the first to the last sample over all devices."""
        ends = [float(f.index[-1]) for f in self.frames.values() if len(f)]
        return max(ends) if ends else 0.0
