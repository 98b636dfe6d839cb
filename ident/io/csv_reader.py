"""Read CSV recordings into device grids (``../shared/spec/telemetry.md``, CSV).

Accepted shapes: ``,`` or ``;`` (or tab) separators, ``.`` or ``,`` decimal marks
(a ``;`` file whose numbers hold a comma), a time column named ``time`` (also
``time_s``, ``timestamp``, ``t``, or an unnamed first column as pandas writes an
index) anywhere among the columns, holding float seconds or ISO-8601 timestamps
(with a zone, or naive and taken as UTC), channel headers ``name`` or
``name [unit]``, leading ``#`` comment lines.  One rate per file; a device written
to ``name.csv`` may have siblings ``name.<device>.csv`` (see
:mod:`ident.io.writers`), which are read with it.

The file is streamed with pyarrow's CSV reader (the engine behind
``pandas.read_csv(engine="pyarrow")``, used directly because pandas' pyarrow engine
cannot read in chunks) into float32 arrays sized by a count of its lines; rows are then
put on a uniform grid of the median time step, where missing rows (dropouts) are NaN.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import RecordingError
from .grid import DeviceGrid, empty_buffer
from . import quality
from .quality import IssueLog

__all__ = ["read_csv", "split_header", "csv_siblings", "first_time", "last_time"]

_UNIT = re.compile(r"^\s*(.*?)\s*\[\s*([^\]]*?)\s*\]\s*$")
_TIME_NAMES = {"time", "time_s", "timestamp", "t", "time [s]"}
_DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d+,\d+([eE][-+]?\d+)?\s*$")


def split_header(name: str) -> tuple[str, str | None]:
    """``"T_C12 [kN*m]"`` -> ``("T_C12", "kN*m")``; ``"T_C12"`` -> ``("T_C12", None)``."""
    m = _UNIT.match(name)
    if m:
        return m.group(1), m.group(2)
    return name.strip(), None


def csv_siblings(path: Path) -> list[Path]:
    """The sibling files ``name.<device>.csv`` of ``name.csv``, sorted."""
    pattern = re.compile(re.escape(path.stem) + r"\.[A-Za-z0-9_\-]+" + re.escape(path.suffix) + "$")
    return sorted(p for p in path.parent.iterdir()
                  if p != path and pattern.match(p.name) and not p.name.startswith(".")
                  and p.is_file())


class _FileLog:
    """The log of one file of a CSV recording (the key file or a sibling device file).

    Fatal errors name this file; findings go to the recording's log, their message
    naming the file when it is a sibling (the finding's path is the key file's).
    """

    def __init__(self, log: IssueLog, path: Path) -> None:
        self.log = log
        self.path = str(path)
        self.tag = "" if self.path == log.path else f"{path.name}: "

    def fatal(self, kind: str, message: str, **kw) -> RecordingError:
        return self.log.fatal(kind, message, path=self.path, **kw)

    def add(self, kind: str, message: str, **kw) -> None:
        self.log.add(kind, self.tag + message, **kw)


def _file_log(log: IssueLog | _FileLog, path: Path) -> _FileLog:
    return log if isinstance(log, _FileLog) and log.path == str(path) else \
        _FileLog(log.log if isinstance(log, _FileLog) else log, path)


def _sniff(path: Path, log: IssueLog) -> tuple[int, str, list[str], list[str], str]:
    """Comment lines, separator, raw column names, first data row, decimal mark."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError as exc:
        raise log.fatal("unreadable", f"cannot read the file ({exc.strerror or exc})") from None
    text = head.decode("utf-8-sig", errors="replace")
    lines = text.splitlines()
    n_comment = 0
    while n_comment < len(lines) and (not lines[n_comment].strip()
                                      or lines[n_comment].lstrip().startswith("#")):
        n_comment += 1
    if n_comment >= len(lines):
        raise log.fatal("unreadable", "the CSV file has no header line; expected "
                        "'time,<channel> [unit],...'")
    header = lines[n_comment]
    counts = {s: header.count(s) for s in (",", ";", "\t")}
    sep = max(counts, key=lambda s: counts[s])
    if counts[sep] == 0:
        raise log.fatal("unreadable", f"the CSV header {header[:80]!r} has no ',', ';' or tab "
                        "separator; expected a time column and at least one channel")
    names = _cells(header, sep)
    first = _cells(lines[n_comment + 1], sep) \
        if n_comment + 1 < len(lines) else []
    decimal = "."
    if sep != "," and any(_DECIMAL_COMMA.match(f) for f in first):
        decimal = ","
    return n_comment, sep, names, first, decimal


def _time_column(names: list[str], log: IssueLog) -> int:
    for i, raw in enumerate(names):
        n, unit = split_header(raw)
        if n.strip().lower() in _TIME_NAMES and unit in (None, "s"):
            return i
    if names and (names[0].strip() == "" or names[0].startswith("Unnamed")):
        return 0
    raise log.fatal("unreadable", f"no time column among {names[:8]}; expected a first column "
                    "'time' (float seconds or ISO-8601)")


#: An empty ISO-8601 time cell, as int64 ns (NumPy's NaT).
_NO_TIME = np.iinfo(np.int64).min


def _iso_to_ns(col, log: IssueLog) -> np.ndarray:
    """ISO-8601 strings (arrow array) -> int64 ns since the epoch (UTC); empty: ``_NO_TIME``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    for ty in (pa.timestamp("ns", tz="UTC"), pa.timestamp("ns")):
        try:
            ns = col.cast(ty).cast(pa.int64())
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
            continue
        if ns.null_count:
            ns = pc.fill_null(ns, _NO_TIME)
        return ns.to_numpy(zero_copy_only=False)
    import pandas as pd

    try:
        ts = pd.to_datetime(col.to_pandas(), format="ISO8601", utc=True)
    except (ValueError, TypeError, OverflowError) as exc:
        raise log.fatal("unreadable", f"time column holds a value that is neither float seconds "
                        f"nor an ISO-8601 timestamp ({exc})") from None
    return ts.to_numpy(dtype="datetime64[ns]").view(np.int64)


def read_csv(path: str, *, keep: Callable[[str], bool], log: IssueLog,
             chunk_samples: int = 1 << 15, siblings: bool = True,
             window_s: tuple[float, float] | None = None) -> list[DeviceGrid]:
    """Read a CSV recording (and its sibling device files) into device grids.

    Parameters
    ----------
    path : str
    keep : callable
        ``keep(channel_name) -> bool``: channels whose samples are kept.
    log : IssueLog
    chunk_samples : int
        Rows parsed per batch (bounds the parser's working memory; at most 2 MB of text
        per batch).
    siblings : bool
        Also read ``name.<device>.csv`` files beside ``name.csv``.
    window_s : (float, float), optional
        Keep only the rows at ``[start, end)`` s from the recording's start (the
        earliest first time over the files); the rest is parsed and dropped batch by
        batch, so memory follows the window.

    Returns
    -------
    list of DeviceGrid
        One per file; the units are those of the header (``""`` when none).
    """
    p = Path(path)
    if not p.is_file():
        raise log.fatal("unreadable", "file not found" if not p.exists() else
                        "not a regular file; expected a CSV recording")
    files = [(p, p.stem)]
    if siblings:
        files += [(s, s.name[len(p.stem) + 1:-len(s.suffix)]) for s in csv_siblings(p)]
    if window_s is None:
        return [_read_one(f, dev, keep=keep, log=log, chunk_samples=chunk_samples)
                for f, dev in files]
    firsts = [first_time(f, log) for f, _ in files]
    origin = min(firsts)
    out = []
    for (f, dev), t_first in zip(files, firsts):
        g = _read_one(f, dev, keep=keep, log=log, chunk_samples=chunk_samples,
                      window=(origin + window_s[0], origin + window_s[1]),
                      origin_ns=_to_ns(origin))
        if g is not None:
            g.origin_ns = _to_ns(origin)
            out.append(g)
    if not out:
        raise log.fatal("empty_window", f"no row between t={window_s[0]:.4f} s and "
                        f"t={window_s[1]:.4f} s from the recording's start",
                        time=float(window_s[0]))
    return out


def _to_ns(t: float) -> int:
    """A file time (float s, or ns as float for ISO files) as int ns."""
    return int(round(t * 1e9))


def _parse_time(text: str, decimal: str, log: IssueLog) -> float:
    """One time cell as float s (ISO-8601 times: s since the Unix epoch)."""
    text = text.strip()
    try:
        return float(text.replace(",", ".") if decimal == "," else text)
    except ValueError:
        pass
    import pandas as pd

    try:
        ts = pd.Timestamp(text)
        ts = ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")
        return ts.value / 1e9
    except (ValueError, TypeError, OverflowError) as exc:
        raise log.fatal("unreadable", f"time cell {text!r} is neither float seconds nor an "
                        f"ISO-8601 timestamp ({exc})") from None


def _offset_before(path: Path, header_lines: int, sep: str, ti: int, decimal: str,
                   t: float, log: IssueLog) -> int:
    """Byte offset of a line start at or before the first row with time >= ``t`` (float s).

    A bisection over the file's bytes (rows in time order, as telemetry.md requires);
    0 when the window starts in the first 1 MB, where reading from the top is as cheap.
    """
    with open(path, "rb") as fh:
        for _ in range(header_lines):
            fh.readline()
        lo, hi = fh.tell(), fh.seek(0, 2)

        def time_at(pos: int) -> tuple[float, int] | None:
            fh.seek(pos)
            if pos:
                fh.readline()  # to the next line start
            start = fh.tell()
            line = fh.readline().decode("utf-8", errors="replace")
            cells = line.rstrip("\r\n").split(sep)
            if len(cells) <= ti or not cells[ti].strip():
                return None
            try:
                return _parse_time(cells[ti], decimal, log), start
            except RecordingError:
                return None

        data_start = lo
        while hi - lo > 1 << 16:
            mid = (lo + hi) // 2
            got = time_at(mid)
            if got is None or got[0] >= t:
                hi = mid
            else:
                lo = mid
        if lo - data_start < 1 << 20:
            return 0
        fh.seek(lo)
        fh.readline()
        return fh.tell()


def first_time(path: Path, log: IssueLog) -> float:
    """The first data row's time, float s (ISO-8601: s since the Unix epoch)."""
    log = _file_log(log, path)
    _, _, names, first, decimal = _sniff(path, log)
    ti = _time_column(names, log)
    if not first or ti >= len(first):
        raise log.fatal("unreadable", "the CSV file has a header but no data rows")
    return _parse_time(first[ti], decimal, log)


def last_time(path: Path, log: IssueLog) -> float:
    """The last data row's time, float s (read from the file's end)."""
    log = _file_log(log, path)
    n_comment, sep, names, first, decimal = _sniff(path, log)
    ti = _time_column(names, log)
    try:
        with open(path, "rb") as fh:
            size = fh.seek(0, 2)
            back = min(size, 1 << 16)
            fh.seek(size - back)
            tail = fh.read().decode("utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise log.fatal("unreadable", f"cannot read the file ({exc.strerror or exc})") from None
    for line in reversed(tail):
        cells = line.split(sep)
        if len(cells) > ti and cells[ti].strip():
            try:
                t = _parse_time(cells[ti], decimal, log)
            except RecordingError:
                continue
            if math.isfinite(t):  # as the reader, which drops rows without a valid time
                return t
    return first_time(path, log)


def _count_lines(path: Path) -> int:
    """Number of lines (a last line without a newline counts), read in 16 MB pieces."""
    count = 0
    last = b"\n"
    with open(path, "rb") as fh:
        while piece := fh.read(1 << 24):
            count += piece.count(b"\n")
            last = piece[-1:]
    return count + (last != b"\n")


_ARROW_CELL = re.compile(r"column #(\d+)\b.*invalid value '(.*)'\s*$", re.S)
_NULLS = ("", "nan", "NaN", "NAN", "null", "NULL", "NA", "N/A", "-nan")


def _cells(line: str, sep: str) -> list[str]:
    """The fields of one line (the csv module's quoting; a plain split if it refuses)."""
    try:
        return next(csv.reader([line], delimiter=sep), [])
    except csv.Error:
        return line.split(sep)


def _parse_error(path: Path, log: _FileLog, exc: BaseException, *, n_comment: int, sep: str,
                 names: list[str], ti: int, first: list[str], decimal: str) -> RecordingError:
    """The error of a CSV file pyarrow cannot parse: the line, channel, time and value.

    pyarrow names the column's position and the value only (its row count restarts with
    each block); this finds the first line holding that value in that column (or, for a
    line with the wrong number of fields, the first such line) by a scan of the file,
    only on this error path.
    """
    m = _ARROW_CELL.search(str(exc))
    col, value = (int(m.group(1)), m.group(2)) if m else (None, None)
    ncols = len(names)

    def time_of(cells: list[str]) -> float | None:
        try:
            t = _parse_time(cells[ti], decimal, log) - _parse_time(first[ti], decimal, log)
        except (RecordingError, IndexError):
            return None
        return t if math.isfinite(t) else None

    found = None
    prev: str | None = None  # the line before
    try:
        with open(path, "rb") as fh:
            for lineno, raw in enumerate(fh, start=1):
                if lineno <= n_comment + 1:
                    continue
                line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
                if not line.strip():
                    continue
                if (value is not None and value not in line) or (
                        value is None and line.count(sep) == ncols - 1 and '"' not in line):
                    prev = line
                    continue
                cells = _cells(line, sep)
                if len(cells) != ncols:
                    found = (lineno, cells, None)
                    break
                if value is not None and col is not None and col < ncols and \
                        cells[col] == value:
                    found = (lineno, cells, col)
                    break
                prev = line
    except OSError:
        found = None
    if found is None:
        return log.fatal("unreadable", f"cannot parse the CSV file: {exc}")
    lineno, cells, col = found
    if col is None:
        t = time_of(cells)
        return log.fatal("unreadable", f"line {lineno} has {len(cells)} fields but the header "
                         f"has {ncols}; expected one value per column", time=t)
    if col == ti:
        t = time_of(_cells(prev, sep)) if prev else None
        after = f" (after t={t:.6f} s)" if t is not None else ""
        return log.fatal("unreadable", f"line {lineno}: the time {value!r} is neither float "
                         f"seconds nor an ISO-8601 timestamp{after}", time=t)
    return log.fatal("unreadable", f"line {lineno}: the value {value!r} is not a number; "
                     "expected a number, or an empty cell, nan or null for a missing sample",
                     channel=split_header(names[col])[0], time=time_of(cells))


def _read_one(path: Path, device: str, *, keep: Callable[[str], bool], log: IssueLog,
              chunk_samples: int, window: tuple[float, float] | None = None,
              origin_ns: int | None = None) -> DeviceGrid | None:
    """One CSV file as a device grid; ``origin_ns`` (the recording's start, as the file's
    times) dates the findings of a windowed read."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    log = _file_log(log, path)
    n_comment, sep, raw_names, first, decimal = _sniff(path, log)
    ti = _time_column(raw_names, log)
    if not first:
        raise log.fatal("unreadable", "the CSV file has a header but no data rows")
    t_first = first[ti].strip() if ti < len(first) else ""
    try:
        float(t_first.replace(",", ".") if decimal == "," else t_first)
        iso = False
    except ValueError:
        iso = True
    col_names = [f"c{i}" for i in range(len(raw_names))]
    parsed = [split_header(n) for n in raw_names]
    all_channels = tuple(parsed[i][0] for i in range(len(parsed)) if i != ti)
    kept = [i for i in range(len(parsed)) if i != ti and keep(parsed[i][0])]
    dup = {parsed[i][0] for i in kept if [parsed[j][0] for j in kept].count(parsed[i][0]) > 1}
    if dup:
        raise log.fatal("unreadable", f"channel(s) {sorted(dup)} appear in more "
                        "than one column")
    types = {col_names[ti]: pa.string() if iso else pa.float64()}
    types.update({col_names[i]: pa.float32() for i in kept})
    row_bytes = max(8, len(sep.join(first)) + 1)
    # pyarrow's streaming reader parses ~30 blocks ahead: small blocks bound its memory
    block = int(min(max(chunk_samples * row_bytes, 1 << 16), 1 << 21))
    reader_opts = pacsv.ReadOptions(skip_rows=n_comment + 1, column_names=col_names,
                                    block_size=block, use_threads=False)
    parse_opts = pacsv.ParseOptions(delimiter=sep)
    conv = pacsv.ConvertOptions(column_types=types, include_columns=[col_names[ti]]
                                + [col_names[i] for i in kept], decimal_point=decimal,
                                null_values=list(_NULLS), strings_can_be_null=True)
    offset = 0
    if window is None:
        cap = max(1, _count_lines(path) - n_comment - 1)  # exact: no growing, no trimming copy
    else:  # start near the window (a bisection over the bytes); grow as rows arrive
        cap = max(chunk_samples, 1 << 12)
        lo_t, hi_t = (int(round(w * 1e9)) for w in window) if iso else window
        offset = _offset_before(path, n_comment + 1, sep, ti, decimal, window[0], log)
        if offset:
            reader_opts = pacsv.ReadOptions(skip_rows=0, column_names=col_names,
                                            block_size=block, use_threads=False)
    t_buf = empty_buffer((cap,), np.int64 if iso else np.float64)
    d_buf = empty_buffer((len(kept), cap), np.float32)
    n = 0
    try:
        source = path
        if offset:
            source = open(path, "rb")  # noqa: SIM115 - closed below
            source.seek(offset)
        reader = pacsv.open_csv(source, read_options=reader_opts, parse_options=parse_opts,
                                convert_options=conv)
        for batch in reader:
            m = batch.num_rows
            sel = None
            if window is not None:
                tcol = batch.column(col_names[ti])
                tv = _iso_to_ns(tcol, log) if iso else tcol.to_numpy(zero_copy_only=False)
                inside = (tv >= lo_t) & (tv < hi_t)
                if not inside.any():
                    if m and np.nanmin(tv) >= hi_t:
                        break  # past the window
                    continue
                sel = np.flatnonzero(inside)
                m = sel.size
            if n + m > t_buf.size:
                new_cap = max(n + m, int(t_buf.size * 1.25))
                nt = empty_buffer((new_cap,), t_buf.dtype)
                nt[:n] = t_buf[:n]
                t_buf = nt
                nd = empty_buffer((len(kept), new_cap), np.float32)
                nd[:, :n] = d_buf[:, :n]
                d_buf = nd
            if sel is not None:
                t_buf[n:n + m] = tv[sel]
                for r, i in enumerate(kept):
                    d_buf[r, n:n + m] = batch.column(col_names[i]).to_numpy(
                        zero_copy_only=False)[sel]
                n += m
                continue
            tcol = batch.column(col_names[ti])
            if iso:
                t_buf[n:n + m] = _iso_to_ns(tcol, log)
            else:
                t_buf[n:n + m] = tcol.to_numpy(zero_copy_only=False)
            for r, i in enumerate(kept):
                d_buf[r, n:n + m] = batch.column(col_names[i]).to_numpy(zero_copy_only=False)
            n += m
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, OSError) as exc:
        raise _parse_error(path, log, exc, n_comment=n_comment, sep=sep, names=raw_names,
                           ti=ti, first=first, decimal=decimal) from None
    finally:
        if offset:
            source.close()
    if n == 0:
        if window is not None:
            return None  # this file holds nothing inside the window
        raise log.fatal("unreadable", "the CSV file has no data rows")
    t_buf = t_buf[:n]
    # a view keeps the spare capacity alive; copy only when that is more than 10 %
    d_buf = d_buf[:, :n] if d_buf.shape[1] <= 1.1 * n else np.ascontiguousarray(d_buf[:, :n])
    if iso:
        bad = t_buf == _NO_TIME
        if bad.any():
            log.add("non_monotonic", f"{int(bad.sum())} rows have no valid time; dropped",
                    device=device, channel=",".join(parsed[i][0] for i in kept))
            t_buf = t_buf[~bad]
            d_buf = d_buf[:, ~bad]
            if not t_buf.size:
                raise log.fatal("unreadable", "no row has a valid time")
        start_ns = int(t_buf[0])
        t_rel = (t_buf - start_ns).astype(np.float64) / 1e9
    else:
        t_rel = t_buf
        bad = ~np.isfinite(t_rel)
        if bad.any():
            log.add("non_monotonic", f"{int(bad.sum())} rows have no valid time; "
                    "dropped", device=device, channel=",".join(parsed[i][0] for i in kept))
            t_rel = t_rel[~bad]
            d_buf = d_buf[:, ~bad]
            if not t_rel.size:
                raise log.fatal("unreadable", "no row has a valid time")
        start = float(t_rel[0])
        # float seconds: an absolute epoch time (>= 1e8 s, 1973) keeps its origin
        start_ns = int(round(start * 1e9))
        t_rel -= start
    return _to_grid(path, device, t_rel, d_buf, start_ns,
                    tuple(parsed[i][0] for i in kept),
                    tuple(parsed[i][1] or "" for i in kept), all_channels, log,
                    t_offset_s=0.0 if origin_ns is None else (start_ns - origin_ns) / 1e9)


_CHUNK = 1 << 20


def _diffs(t: np.ndarray):
    """Yield ``(offset, np.diff(t)[offset:offset + len])`` in chunks (bounded memory)."""
    for s in range(0, t.size - 1, _CHUNK):
        yield s, np.diff(t[s:min(s + _CHUNK + 1, t.size)])


def _to_grid(path: Path, device: str, t: np.ndarray, data: np.ndarray, start_ns: int,
             channels: tuple[str, ...], units: tuple[str, ...], all_channels: tuple[str, ...],
             log: _FileLog, *, t_offset_s: float = 0.0) -> DeviceGrid:
    """Put rows with times ``t`` (s from the first) on a uniform grid; report what is off.

    ``t_offset_s``: time of the first row from the recording's start (a windowed read).
    Time that steps back or repeats is an error (telemetry.md: the order of samples is
    not guessed).
    """
    names = ",".join(channels)
    n = t.size
    if n < 2:
        raise log.fatal("unreadable", "a single row; cannot tell the sample rate",
                        channel=names)
    back = next((s + np.flatnonzero(d <= 0) for s, d in _diffs(t) if (d <= 0).any()), None)
    if back is not None:
        i = int(back[0])
        n_back = sum(int((d <= 0).sum()) for _, d in _diffs(t))
        a, b = float(t[i]) + t_offset_s, float(t[i + 1]) + t_offset_s
        what = f"repeats: t={b:.6f} s twice" if t[i + 1] == t[i] else \
            f"steps back from t={a:.6f} s to t={b:.6f} s"
        more = f" ({n_back} rows in all are not after the row before)" if n_back > 1 else ""
        raise log.fatal("non_monotonic", f"time {what}{more}; expected strictly increasing "
                        "times: the order of samples is not guessed", time=b)
    jump = next(((s + int(np.argmax(d)), float(d.max())) for s, d in _diffs(t)
                 if d.max() > quality.MAX_DROPOUT_S), None)
    if jump is not None:
        i, d = jump
        raise log.fatal("time_jump", f"time jumps from t={t[i] + t_offset_s:.6f} s to "
                        f"t={t[i + 1] + t_offset_s:.6f} s: no row for {d:.6g} s, longer than a "
                        f"dropout may last ({quality.MAX_DROPOUT_S:g} s); a wrong time stamp?",
                        channel=names, time=float(t[i + 1]) + t_offset_s)
    dt = float(np.median(np.diff(t[:2_000_001])))  # the first 2e6 steps tell the rate
    span = float(t[-1] - t[0])
    rate = 1.0 / dt
    if abs(span / (n - 1) - dt) <= 0.01 * dt:  # no gaps: the whole span is the best estimate
        rate = (n - 1) / span
    if abs(rate - round(rate)) <= 1e-5 * rate:
        rate = float(round(rate))
    if not math.isfinite(rate) or rate <= 0:
        raise log.fatal("rate_mismatch", "cannot tell the sample rate",
                        channel=names)
    n_odd = 0
    first_odd: tuple[int, float] | None = None
    big_at: list[np.ndarray] = []
    big_len: list[np.ndarray] = []
    for s, d in _diffs(t):
        steps = np.rint(d * rate)
        odd = (np.abs(d * rate - steps) > 0.25) | (steps < 1)
        big = (steps > 1) & ~odd
        n_odd += int(odd.sum())
        if first_odd is None and odd.any():
            j = int(np.flatnonzero(odd)[0])
            first_odd = (s + j + 1, float(d[j]))
        if big.any():
            big_at.append(s + np.flatnonzero(big))
            big_len.append(steps[big].astype(np.int64) - 1)
    n_big = int(sum(b.size for b in big_at))
    if n_odd > 0.01 * n or n_big > max(3, 0.01 * n):
        if first_odd is None:
            first_odd = (int(big_at[0][0]) + 1, float(t[big_at[0][0] + 1] - t[big_at[0][0]]))
        raise log.fatal("rate_mismatch", f"the time steps are not one rate: the median step "
                        f"is {dt:.6g} s ({rate:.6g} Hz) but {n_odd + n_big} of {n - 1} steps "
                        f"differ (e.g. {first_odd[1]:.6g} s); expected one rate per file",
                        channel=names, time=float(t[first_odd[0]]) + t_offset_s)
    if n_odd:
        t_odd = float(t[first_odd[0]]) + t_offset_s
        log.add("non_monotonic", f"{n_odd} time steps are off the {rate:g} Hz grid by more "
                f"than a quarter sample (first at t={t_odd:.6f} s); rows put on the nearest "
                "grid point", channel=names, t_start=t_odd, device=device)
    gaps: list[tuple[int, int]] = []
    time_buffer: np.ndarray | None = t if t.dtype == np.float64 else None
    if n_big:
        at = np.concatenate(big_at)
        extra = np.concatenate(big_len)
        shift = np.zeros(n, dtype=np.int64)
        shift[at + 1] = extra
        pos = np.arange(n, dtype=np.int64) + np.cumsum(shift)
        grid = empty_buffer((data.shape[0], int(pos[-1]) + 1), np.float32)
        grid.fill(np.nan)
        grid[:, pos] = data
        data = grid
        for j in at.tolist():
            gaps.append((int(pos[j]) + 1, int(pos[j + 1])))
        time_buffer = None
    return DeviceGrid(name=device, rate_hz=rate, start_ns=start_ns, channels=channels,
                      units=units, data=data, gaps=gaps, all_channels=all_channels,
                      time_buffer=time_buffer)
