"""Read a mill description file (TOML, ``../shared/spec/mill-config.md``)."""

from __future__ import annotations

import hashlib
import re
import tomllib
from pathlib import Path

from ..description import Mill
from ..errors import MillFileError
from ..schema import mill_from_mapping

__all__ = ["load_mill", "parse_mill"]


def _locator(text: str):
    """Return ``locate(table, index, key) -> line`` by scanning the TOML text."""
    lines = text.splitlines()
    header = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?\s*(#.*)?$")
    # (table, index or None, first line, last line)
    spans: list[tuple[str, int | None, int, int]] = []
    counts: dict[str, int] = {}
    for n, ln in enumerate(lines, start=1):
        m = header.match(ln)
        if m:
            name = m.group(1)
            if ln.strip().startswith("[["):
                idx = counts.get(name, 0)
                counts[name] = idx + 1
            else:
                idx = None
            if spans:
                t, i, s, _ = spans[-1]
                spans[-1] = (t, i, s, n - 1)
            spans.append((name, idx, n, len(lines)))

    def key_line(key: str, first: int, last: int) -> int | None:
        kre = re.compile(rf"^\s*[\"']?{re.escape(key)}[\"']?\s*=")
        for n in range(first, last + 1):
            if kre.match(lines[n - 1]):
                return n
        return None

    def locate(table: str, index: int | None, key: str | None) -> int | None:
        if not table:  # a top-level key, before the first table header
            end = spans[0][2] - 1 if spans else len(lines)
            return key_line(key, 1, end) if key else None
        for t, i, s, e in spans:
            if t == table and (index is None or i == index):
                if key is None:
                    return s
                n = key_line(key, s, e)
                if n is not None:
                    return n
                # a sub-table [table.key] of this entry: its header (or the entry's)
                sub = [s2 for t2, _, s2, _ in spans if t2 == f"{table}.{key}" and s2 > s]
                return sub[0] if sub else s
        return None

    return locate


def parse_mill(text: str, *, path: str | None = None) -> Mill:
    """Parse mill-file text into a validated :class:`~ident.description.Mill`.

    Raises
    ------
    MillFileError
        Invalid TOML or content, naming the path, key and line.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"line (\d+)", str(exc))
        raise MillFileError(f"not valid TOML: {exc}", path=path,
                            line=int(m.group(1)) if m else None) from None
    sha = hashlib.sha256(text.encode()).hexdigest()
    return mill_from_mapping(data, path=path, locate=_locator(text), sha256=sha)


def load_mill(path: str | Path) -> Mill:
    """Load and validate a mill file.

    Parameters
    ----------
    path : str or Path
        The TOML file.

    Returns
    -------
    Mill
        The immutable description; ``mill.sha256`` is the hash of the file's text.

    Raises
    ------
    MillFileError
        The file is missing, not TOML, or violates the contract.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MillFileError("mill file not found", path=str(p)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MillFileError(f"cannot read mill file: {exc}", path=str(p)) from None
    return parse_mill(text, path=str(p))
