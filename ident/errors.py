"""Typed errors and warnings of ident.

Every error a user can cause derives from :class:`IdentError` and also from a
builtin (``ValueError``) so that generic handlers still catch it.  The command
line maps ``IdentError`` to exit code 2 and anything else to exit code 1.
"""

from __future__ import annotations

__all__ = [
    "IdentError",
    "MillFileError",
    "RecordingError",
    "FitError",
    "ModelArtifactError",
    "StoreError",
    "ConvergenceWarning",
    "DataQualityWarning",
]


class IdentError(Exception):
    """Base class of every error caused by the user's input."""


class MillFileError(IdentError, ValueError):
    """A mill description file is malformed.

    Parameters
    ----------
    message : str
        What is wrong, what was given and what was expected.
    path : str or None
        The mill file.
    key : str or None
        The dotted key, e.g. ``element[C46].gap``.
    line : int or None
        1-based line in the file where the key stands, when known.
    """

    def __init__(self, message: str, *, path: str | None = None, key: str | None = None,
                 line: int | None = None) -> None:
        self.path = path
        self.key = key
        self.line = line
        #: the message without the file, line and key in front
        self.reason = message
        where = []
        if path:
            where.append(str(path) + (f":{line}" if line else ""))
        elif line:
            where.append(f"line {line}")
        if key:
            where.append(f"key '{key}'")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class RecordingError(IdentError, ValueError):
    """A recording is unreadable, or its content contradicts the mill file.

    Parameters
    ----------
    message : str
        What is wrong.
    path : str or None
        The recording file.
    channel : str or None
        The channel concerned.
    time : float or None
        Seconds from the recording's start where the problem is.
    """

    def __init__(self, message: str, *, path: str | None = None, channel: str | None = None,
                 time: float | None = None) -> None:
        self.path = path
        self.channel = channel
        self.time = time
        #: the message without the file, channel and time in front
        self.reason = message
        where = []
        if path:
            where.append(str(path))
        if channel:
            where.append(f"channel '{channel}'")
        if time is not None:
            where.append(f"t={time:.6f} s")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class FitError(IdentError, RuntimeError):
    """An identification could not be carried out or did not converge."""


class ModelArtifactError(IdentError, ValueError):
    """A saved classifier does not match the mill file or library versions."""


class StoreError(IdentError, RuntimeError):
    """The results store cannot be opened or written."""


class ConvergenceWarning(UserWarning):
    """An optimiser stopped without meeting its tolerance."""


class DataQualityWarning(UserWarning):
    """A recording has a quality problem that does not prevent its use."""
