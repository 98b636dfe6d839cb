"""Find the recordings under a campaign folder and hash their content.

Recordings are ``*.mcap`` and ``*.csv`` files at any depth (hidden files and
folders, and names starting with ``_`` or ``.`` are left out).  A CSV holds one
rate (telemetry.md), so a CSV recording of two devices is several files; the
CSV writer names the siblings ``STEM.csv`` plus ``STEM.<device>.csv`` (see
:data:`CSV_SIBLING_SEP`), and they are grouped into one recording keyed by the
``STEM.csv`` file.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import RecordingError

__all__ = ["RecordingSource", "discover", "content_hash", "RECORDING_SUFFIXES",
           "CSV_SIBLING_SEP"]

RECORDING_SUFFIXES = (".mcap", ".csv")
#: ``rec.csv`` and ``rec<SEP>accel.csv`` are the devices of one CSV recording.
CSV_SIBLING_SEP = "."


@dataclass(frozen=True)
class RecordingSource:
    """One recording as found on disk.

    Attributes
    ----------
    file_name : str
        The key file's path relative to the campaign folder, ``/``-separated.
    paths : tuple of Path
        The key file first, then its sibling files (CSV devices), absolute.
    size_bytes : int
        Total size of all member files.
    content_sha256 : str
        SHA-256 of the key file's bytes when it stands alone; with siblings, the
        SHA-256 over every member's name and SHA-256.
    """

    file_name: str
    paths: tuple[Path, ...]
    size_bytes: int
    content_sha256: str

    @property
    def path(self) -> Path:
        """The file that readers open (siblings are found from it)."""
        return self.paths[0]

    def member_names(self, root: Path) -> list[str]:
        return [p.relative_to(root).as_posix() for p in self.paths]


def _file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def content_hash(paths: tuple[Path, ...]) -> str:
    """SHA-256 identifying the content of one recording's member files."""
    if len(paths) == 1:
        return _file_sha256(paths[0])
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode() + b"\0" + _file_sha256(p).encode() + b"\n")
    return h.hexdigest()


def _visible(rel: Path) -> bool:
    return not any(part.startswith((".", "_")) for part in rel.parts)


def _group_csv(files: list[Path]) -> list[tuple[Path, ...]]:
    """Group ``STEM.csv`` with its ``STEM.<device>.csv`` siblings in the same folder."""
    stems = {(p.parent, p.stem): p for p in files}
    groups: dict[Path, list[Path]] = {}
    for p in files:
        owner = p
        stem = p.stem
        while CSV_SIBLING_SEP in stem:
            stem = stem.rsplit(CSV_SIBLING_SEP, 1)[0]
            if (p.parent, stem) in stems:
                owner = stems[(p.parent, stem)]
                break
        groups.setdefault(owner, []).append(p)
    return [tuple([k] + sorted(v for v in vs if v != k)) for k, vs in groups.items()]


def _unreadable_hash(paths: tuple[Path, ...], exc: OSError) -> str:
    """A key for files that cannot be read now (it changes when they change)."""
    h = hashlib.sha256(b"unreadable")
    for p in paths:
        try:
            st = p.stat()
            h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns}".encode())
        except OSError:
            h.update(p.name.encode())
    return "unreadable-" + h.hexdigest()[:52]


def discover(directory: str | os.PathLike, *, hash_content: bool = True,
             min_age_s: float = 0.0) -> list[RecordingSource]:
    """The recordings under ``directory``, sorted by file name.

    Parameters
    ----------
    directory : path
        The campaign folder, searched recursively.
    hash_content : bool
        Compute ``content_sha256`` (reads every byte); with False it is empty.  A file
        that cannot be read gets a key starting ``unreadable-`` (its processing then
        fails with the reader's reason).
    min_age_s : float
        Leave out recordings modified less than this many seconds ago (files still
        being copied in).

    Raises
    ------
    RecordingError
        ``directory`` does not exist or is not a folder.
    """
    root = Path(directory)
    if not root.exists():
        raise RecordingError("campaign folder not found", path=str(root))
    if not root.is_dir():
        raise RecordingError("the campaign path is not a folder", path=str(root))
    root = root.resolve()
    mcap, csv = [], []
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = Path(dirpath).relative_to(root)
        dirnames[:] = sorted(d for d in dirnames if _visible(rel_dir / d))
        for f in filenames:
            rel = rel_dir / f
            if not _visible(rel):
                continue
            suf = Path(f).suffix.lower()
            if suf == ".mcap":
                mcap.append(root / rel)
            elif suf == ".csv":
                csv.append(root / rel)
    groups = [(p,) for p in mcap] + _group_csv(csv)
    out = []
    now = time.time()
    for paths in groups:
        try:
            stats = [p.stat() for p in paths]
        except OSError:  # vanished since the walk
            continue
        if min_age_s > 0 and now - max(st.st_mtime for st in stats) < min_age_s:
            continue
        digest = ""
        if hash_content:
            try:
                digest = content_hash(paths)
            except OSError as exc:
                digest = _unreadable_hash(paths, exc)
        out.append(RecordingSource(file_name=paths[0].relative_to(root).as_posix(), paths=paths,
                                   size_bytes=sum(st.st_size for st in stats),
                                   content_sha256=digest))
    return sorted(out, key=lambda s: s.file_name)
