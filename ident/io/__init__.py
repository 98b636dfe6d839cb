"""Reading mill files and recordings; writing recordings.

* :func:`load_mill` / :func:`parse_mill`: the mill description file.
* :func:`read_recording`: MCAP or CSV telemetry into SI DataFrames, with quality
  findings (:mod:`ident.io.quality`), whole or a time window; :func:`iter_recording`
  walks a long recording window by window with bounded memory;
  :func:`reduced_torques`, :func:`align_devices`.
* :func:`write_recording`: MCAP (protobuf or JSON sample blocks) or CSV.
"""
from .millfile import load_mill, parse_mill
from .readers import (align_devices, iter_recording, read_recording, recording_span,
                      reduced_torques)
from .recording import QualityIssue, RawDevice, Recording
from .writers import write_recording

__all__ = ["load_mill", "parse_mill", "read_recording", "iter_recording", "recording_span",
           "write_recording", "reduced_torques",
           "align_devices", "Recording", "RawDevice", "QualityIssue"]
