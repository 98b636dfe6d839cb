"""Open a results store by SQLAlchemy URL and write one recording per transaction.

SQLite is the embedded default (``sqlite:///results.db``); PostgreSQL is reached by
``postgresql+psycopg://user@host/db`` (``postgresql://`` is read as psycopg 3).
Only the campaign's parent process writes, so SQLite sees a single writer; readers
(the report, a notebook) may read while a campaign runs (SQLite in WAL mode).

:meth:`Store.write_outcome` writes a recording row and every row that belongs to
it in one transaction: a crash before the commit leaves nothing of that
recording, a crash after it loses nothing.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from ..description import Mill
from ..errors import StoreError
from . import schema as S
from .outcome import RecordingOutcome, jsonable

__all__ = ["Store", "open_store", "RecordingKey", "normalize_url"]


@dataclass(frozen=True)
class RecordingKey:
    """What identifies a stored recording.

    Attributes
    ----------
    file_name : str
        Path relative to the campaign folder, ``/``-separated.
    content_sha256 : str
        SHA-256 of the recording's bytes (all member files, in order).
    settings_hash : str
        Hash of the processing settings and the mill description.
    """

    file_name: str
    content_sha256: str
    settings_hash: str


def _utcnow() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def _num(x: Any) -> float | None:
    """A finite float or None (NaN/inf/None/non-numbers are stored as NULL)."""
    if x is None or isinstance(x, bool):
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _int(x: Any) -> int | None:
    v = _num(x)
    return None if v is None else int(v)


def normalize_url(url: str) -> str:
    """Return ``url`` with PostgreSQL's default driver set to psycopg 3.

    Raises
    ------
    StoreError
        ``url`` is not an SQLAlchemy database URL.
    """
    if not isinstance(url, str) or not url.strip():
        raise StoreError(f"the store URL must be an SQLAlchemy database URL such as "
                         f"sqlite:///results.db. Got {url!r}")
    try:
        u = sa.engine.make_url(url.strip())
    except sa.exc.ArgumentError:
        raise StoreError(f"the store URL must be an SQLAlchemy database URL such as "
                         f"sqlite:///results.db or postgresql+psycopg://user@host/db. "
                         f"Got {url!r}") from None
    if u.drivername in ("postgresql", "postgres"):
        u = u.set(drivername="postgresql+psycopg")
    return u.render_as_string(hide_password=False)


def _sqlite_pragmas(dbapi_conn, _record) -> None:  # pragma: no cover - driver callback
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()


def open_store(url: str, *, create: bool = True) -> "Store":
    """Open (and by default create) the results store at ``url``.

    Parameters
    ----------
    url : str
        SQLAlchemy URL: ``sqlite:///path/results.db`` or
        ``postgresql+psycopg://user@host:port/db``.
    create : bool
        Create the tables (and an SQLite file with its folder) when missing.  With
        ``False`` a store that does not exist is an error (what ``ident report`` wants).

    Returns
    -------
    Store

    Raises
    ------
    StoreError
        Bad URL, missing database driver, unreachable server, a missing store with
        ``create=False``, or a store of another schema version.
    """
    url = normalize_url(url)
    u = sa.engine.make_url(url)
    kwargs: dict[str, Any] = {}
    if u.get_backend_name() == "sqlite":
        db = u.database
        if db and db != ":memory:" and not db.startswith("file:"):
            p = Path(db)
            if not p.exists():
                if not create:
                    raise StoreError(f"results store not found: {p} (from {url!r})")
                p.parent.mkdir(parents=True, exist_ok=True)
        kwargs["connect_args"] = {"timeout": 60}
    try:
        engine = sa.create_engine(url, **kwargs)
    except (sa.exc.NoSuchModuleError, ModuleNotFoundError, ImportError) as exc:
        raise StoreError(f"no database driver for {u.drivername!r} ({exc}); for PostgreSQL "
                         f"install psycopg: pip install 'psycopg[binary]'") from None
    except sa.exc.ArgumentError as exc:
        raise StoreError(f"bad store URL {url!r}: {exc}") from None
    if u.get_backend_name() == "sqlite":
        sa.event.listen(engine, "connect", _sqlite_pragmas)
    store = Store(engine)
    try:
        store._prepare(create=create)
    except StoreError:
        engine.dispose()
        raise
    except sa.exc.SQLAlchemyError as exc:
        engine.dispose()
        raise StoreError(f"cannot open the results store "
                         f"{u.render_as_string(hide_password=True)}: "
                         f"{str(exc.orig if hasattr(exc, 'orig') and exc.orig else exc).strip()}"
                         ) from None
    return store


class Store:
    """A results store: an SQLAlchemy engine on the tables of :mod:`ident.store.schema`.

    Make it with :func:`open_store`; close it with :meth:`close` (or use it as a
    context manager).
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine

    # ---- life cycle ---------------------------------------------------------------
    @property
    def url(self) -> str:
        """The URL without password."""
        return self.engine.url.render_as_string(hide_password=True)

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _prepare(self, *, create: bool) -> None:
        insp = sa.inspect(self.engine)
        present = set(insp.get_table_names())
        if not create and "schema_info" not in present:
            raise StoreError(f"{self.url} is not an ident results store (no schema_info table)")
        if create:
            try:
                S.metadata.create_all(self.engine)
            except (sa.exc.OperationalError, sa.exc.ProgrammingError) as exc:
                if "already exists" not in str(exc):
                    raise
                S.metadata.create_all(self.engine)  # another process created some tables first
        row = self._schema_row()
        if row is None:
            if not create:
                raise StoreError(f"{self.url} is being created (no schema version written "
                                 f"yet); open it again in a moment")
            try:
                with self.engine.begin() as conn:
                    conn.execute(S.schema_info.insert().values(key="schema_version",
                                                               value=str(S.SCHEMA_VERSION)))
                return
            except sa.exc.IntegrityError:
                # another process created the store at the same moment: read its version
                row = self._schema_row()
        with self.engine.begin() as conn:
            try:
                version = int(row[0])
            except ValueError:
                version = -1
            if version > S.SCHEMA_VERSION or version < 1:
                raise StoreError(f"{self.url} holds schema version {row[0]}; this ident "
                                 f"reads version {S.SCHEMA_VERSION} (and migrates older ones)")
            if version < S.SCHEMA_VERSION:
                self._migrate(conn, version)

    def _schema_row(self) -> Any:
        with self.engine.connect() as conn:
            return conn.execute(sa.select(S.schema_info.c.value)
                                .where(S.schema_info.c.key == "schema_version")).first()

    def _migrate(self, conn: Connection, version: int) -> None:
        """Bring a store of an older schema version up to :data:`~ident.store.schema.SCHEMA_VERSION`.

        Every version so far only added tables and nullable columns (or columns with
        a default): the missing ones are added, every row is kept, and the version is
        written last.  Each step is idempotent, so a migration interrupted half-way
        is finished by the next :func:`open_store`.
        """
        S.metadata.create_all(conn)  # tables new since that version
        insp = sa.inspect(conn)
        preparer = conn.dialect.identifier_preparer
        for table in S.metadata.sorted_tables:
            have = {c["name"] for c in insp.get_columns(table.name)}
            for col in table.columns:
                if col.name in have:
                    continue
                ddl = (f"ALTER TABLE {preparer.format_table(table)} ADD COLUMN "
                       f"{preparer.format_column(col)} {col.type.compile(dialect=conn.dialect)}")
                if col.server_default is not None:
                    ddl += f" DEFAULT {col.server_default.arg.text}"
                conn.execute(sa.text(ddl))
        conn.execute(S.schema_info.update().where(S.schema_info.c.key == "schema_version")
                     .values(value=str(S.SCHEMA_VERSION)))

    # ---- reading ------------------------------------------------------------------
    def stored_keys(self, settings_hash: str) -> dict[tuple[str, str], str]:
        """``{(file_name, content_sha256): status}`` of recordings stored with these settings."""
        r = S.recordings.c
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(r.file_name, r.content_sha256, r.status)
                                .where(r.settings_hash == settings_hash)).all()
        return {(f, h): s for f, h, s in rows}

    def failed_errors(self, settings_hash: str) -> dict[tuple[str, str], str]:
        """``{(file_name, content_sha256): error}`` of recordings stored as failed."""
        r = S.recordings.c
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(r.file_name, r.content_sha256, r.error).where(
                r.settings_hash == settings_hash, r.status == "failed")).all()
        return {(f, h): e or "" for f, h, e in rows}

    def fit_summaries(self, settings_hash: str) -> list[dict[str, Any]]:
        """The whole-recording fits of the recordings stored ``done`` with these settings.

        Returns
        -------
        list of dict
            ``{"file_name", "content_sha256", "t0_ns", "gaps": {element: rad},
            "identified": set of element ids}`` per recording with a fit, in
            ``(t0_ns, file_name)`` order.
        """
        r, e = S.recordings.c, S.element_results.c
        q = (sa.select(r.file_name, r.content_sha256, r.t0_ns, e.element, e.gap, e.identifiable)
             .join(S.element_results, e.recording_pk == r.id)
             .where(r.settings_hash == settings_hash, r.status == "done",
                    e.transient_idx.is_(None)))
        out: dict[tuple[str, str], dict[str, Any]] = {}
        with self.engine.connect() as conn:
            for f, h, t0, el, gap, ident_ in conn.execute(q):
                d = out.setdefault((f, h), {"file_name": f, "content_sha256": h, "t0_ns": t0,
                                            "gaps": {}, "identified": set()})
                if gap is not None:
                    d["gaps"][el] = float(gap)
                if ident_:
                    d["identified"].add(el)
        return sorted(out.values(), key=lambda d: (d["t0_ns"] or 0, d["file_name"]))

    def count(self, table: str = "recordings", **where: Any) -> int:
        """Number of rows in ``table`` matching ``column=value`` conditions."""
        t = S.metadata.tables[table]
        q = sa.select(sa.func.count()).select_from(t)
        for k, v in where.items():
            q = q.where(t.c[k] == v)
        with self.engine.connect() as conn:
            return int(conn.execute(q).scalar_one())

    # ---- writing ------------------------------------------------------------------
    def register_mill(self, mill: Mill, text: str) -> None:
        """Keep the mill file (by its text's SHA-256) so that reports can read its limits."""
        with self.engine.begin() as conn:
            exists = conn.execute(sa.select(S.mills.c.sha256)
                                  .where(S.mills.c.sha256 == mill.sha256)).first()
            if exists is None:
                conn.execute(S.mills.insert().values(
                    sha256=mill.sha256, name=mill.name, content_hash=mill.content_hash(),
                    text=text, first_seen=_utcnow()))

    def start_run(self, *, directory: str, mill: Mill, settings_hash: str,
                  settings: Mapping[str, Any], executor: str, host: str,
                  versions: Mapping[str, str], n_found: int, n_skipped: int) -> int:
        """Log the start of a campaign run; returns its id."""
        with self.engine.begin() as conn:
            res = conn.execute(S.runs.insert().values(
                started_at=_utcnow(), status="running", directory=directory,
                mill_name=mill.name, mill_sha256=mill.sha256, settings_hash=settings_hash,
                settings=jsonable(dict(settings)), executor=executor, host=host,
                versions=dict(versions), n_found=n_found, n_skipped=n_skipped, n_done=0,
                n_failed=0))
            return int(res.inserted_primary_key[0])

    def finish_run(self, run_id: int, *, status: str, n_done: int, n_failed: int) -> None:
        """Record how a run ended (``finished`` or ``interrupted``)."""
        with self.engine.begin() as conn:
            conn.execute(S.runs.update().where(S.runs.c.id == run_id).values(
                finished_at=_utcnow(), status=status, n_done=n_done, n_failed=n_failed))

    def write_outcome(self, run_id: int, key: RecordingKey, outcome: RecordingOutcome, *,
                      mill: Mill, files: Iterable[str], size_bytes: int,
                      replace: bool = False) -> bool:
        """Write one recording and all its rows in ONE transaction.

        Parameters
        ----------
        run_id : int
        key : RecordingKey
        outcome : RecordingOutcome
        mill : Mill
            The description the outcome was computed with (registered beforehand
            with :meth:`register_mill`).
        files : iterable of str
            Member file names (relative to the campaign folder).
        size_bytes : int
        replace : bool
            Delete a row already stored under ``key`` first (retrying a failed one).

        Returns
        -------
        bool
            True if written; False if ``key`` was already stored (by a concurrent run)
            and ``replace`` is False.
        """
        rows = outcome_rows(outcome)
        try:
            with self.engine.begin() as conn:
                if replace:
                    self._delete(conn, key)
                rec = _recording_row(run_id, key, outcome, mill=mill, files=list(files),
                                     size_bytes=size_bytes)
                res = conn.execute(S.recordings.insert().values(**rec))
                pk = int(res.inserted_primary_key[0])
                self._insert_children(conn, pk, rows)
        except sa.exc.IntegrityError:
            if replace:
                raise
            return False
        return True

    def _insert_children(self, conn: Connection, pk: int,
                         rows: Mapping[str, list[dict[str, Any]]]) -> None:
        for table in S.CHILD_TABLES:
            batch = rows.get(table.name) or []
            if batch:
                conn.execute(table.insert(), [dict(r, recording_pk=pk) for r in batch])

    def _delete(self, conn: Connection, key: RecordingKey) -> None:
        r = S.recordings.c
        pks = [p for (p,) in conn.execute(sa.select(r.id).where(
            r.file_name == key.file_name, r.content_sha256 == key.content_sha256,
            r.settings_hash == key.settings_hash))]
        if not pks:
            return
        for table in S.CHILD_TABLES:
            conn.execute(table.delete().where(table.c.recording_pk.in_(pks)))
        conn.execute(S.recordings.delete().where(r.id.in_(pks)))


# ---- outcome -> rows ----------------------------------------------------------------
def _recording_row(run_id: int, key: RecordingKey, o: RecordingOutcome, *, mill: Mill,
                   files: list[str], size_bytes: int) -> dict[str, Any]:
    rec = o.recording or {}
    meta = jsonable(dict(rec.get("metadata") or {}))
    rid = rec.get("recording_id") or meta.get("recording_id")
    started = (_dt.datetime.fromtimestamp(o.started_at, _dt.timezone.utc)
               if o.started_at else None)
    finished = (_dt.datetime.fromtimestamp(o.started_at + o.elapsed_s, _dt.timezone.utc)
                if o.started_at else None)
    return {
        "run_id": run_id, "file_name": key.file_name, "content_sha256": key.content_sha256,
        "size_bytes": int(size_bytes), "files": files, "settings_hash": key.settings_hash,
        "mill_name": mill.name, "mill_sha256": mill.sha256, "status": o.status,
        "error": o.error, "error_kind": o.error_kind, "stage": o.stage,
        "recording_id": None if rid is None else str(rid), "metadata": meta,
        "t0_ns": _int(rec.get("t0_ns")), "duration_s": _num(rec.get("duration_s")),
        "n_transients": len(o.segments), "versions": dict(o.versions),
        "started_at": started, "finished_at": finished, "elapsed_s": _num(o.elapsed_s),
        "worker": o.worker or None,
    }


_SEGMENT_KEYS = ("t_start", "t_step", "t_end", "kind", "static_torque", "step")


def _fit_rows(fit: Mapping[str, Any], tidx: int | None) -> tuple[dict, list[dict]]:
    metrics = fit.get("metrics") or {}
    solver = fit.get("solver") or {}
    family = fit.get("family")
    frow = {"transient_idx": tidx, "family": family, "nrmse": _num(metrics.get("nrmse")),
            "nrmse_linear": _num(metrics.get("nrmse_linear")),
            "solver_status": None if solver.get("status") is None else str(solver["status"]),
            "solver_iterations": _int(solver.get("iterations")),
            "solver_seconds": _num(solver.get("seconds")), "result": jsonable(dict(fit))}
    erows = []
    for eid, e in (fit.get("elements") or {}).items():
        ci = e.get("gap_ci95") or [None, None]
        # the fit's verdict (identified); older fit JSON had only the identifiable flag
        ident_ = e.get("identified", e.get("identifiable"))
        erows.append({"transient_idx": tidx, "element": str(eid), "family": family,
                      "gap": _num(e.get("gap")), "gap_ci_lo": _num(ci[0]),
                      "gap_ci_hi": _num(ci[1]), "gap_open": _num(e.get("gap_open")),
                      "gap_mm": _num(e.get("gap_mm")),
                      "params": jsonable(dict(e.get("params") or {})),
                      "identifiable": None if ident_ is None else bool(ident_)})
    return frow, erows


def _verdict_rows(diagnosis: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``diagnoses`` rows of a cli.md ``diagnose`` JSON: one verdict per element and bearing."""
    rows = []
    for kind, key, size in (("element", "elements", "gap"), ("bearing", "bearings", "clearance")):
        for tid, v in (diagnosis.get(key) or {}).items():
            ci = v.get(f"{size}_ci95") or [None, None]
            uncertain = v.get("uncertain")
            rows.append({
                "transient_idx": None, "kind": kind, "target": str(tid), "state": v.get("state"),
                "probability": _num(v.get("probability")),
                "gap": _num(v.get("gap")) if kind == "element" else None,
                "clearance": _num(v.get("clearance")) if kind == "bearing" else None,
                # a diagnose JSON without a source (older ident) came from the model
                "source": str(v.get("source") or "diagnosis"),
                "value_ci_lo": _num(ci[0]), "value_ci_hi": _num(ci[1]),
                "uncertain": None if uncertain is None else bool(uncertain),
                "reason": v.get("reason") or None})
    return rows


def outcome_rows(o: RecordingOutcome) -> dict[str, list[dict[str, Any]]]:
    """The child-table rows of an outcome, keyed by table name (without ``recording_pk``).

    Reads only the documented JSON shapes; unknown keys of a segment go to ``extra``,
    missing optional keys become NULL.
    """
    out: dict[str, list[dict[str, Any]]] = {t.name: [] for t in S.CHILD_TABLES}
    for i, seg in enumerate(o.segments):
        out["transients"].append({
            "transient_idx": i, "kind": str(seg.get("kind", "")),
            "t_start": _num(seg.get("t_start")), "t_step": _num(seg.get("t_step")),
            "t_end": _num(seg.get("t_end")), "static_torque": _num(seg.get("static_torque")),
            "step": _num(seg.get("step")),
            "extra": jsonable({k: v for k, v in seg.items() if k not in _SEGMENT_KEYS}) or None})
    for row in o.taf:
        out["taf"].append({
            "transient_idx": _int(row.get("transient_idx")), "element": str(row["element"]),
            "channel": str(row.get("channel") or ""),
            "static_torque": _num(row.get("static_torque")),
            "peak_torque": _num(row.get("peak_torque")), "taf": _num(row.get("taf"))})
    fits = ([(None, o.fit)] if o.fit else []) + [
        (_int(f.get("transient_idx")), f) for f in o.transient_fits]
    for tidx, fit in fits:
        frow, erows = _fit_rows(fit, tidx)
        out["fits"].append(frow)
        out["element_results"].extend(erows)
    if o.diagnosis:
        d = o.diagnosis
        out["diagnoses"].extend(_verdict_rows(d))
        for name, values in (d.get("features") or {}).items():
            if isinstance(values, (list, tuple)):
                for j, v in enumerate(values):
                    out["features"].append({"transient_idx": None, "name": str(name),
                                            "idx": j, "value": _num(v)})
            elif _num(values) is not None:
                out["features"].append({"transient_idx": None, "name": str(name), "idx": 0,
                                        "value": _num(values)})
    for q in o.quality:
        out["quality_issues"].append({
            "transient_idx": None, "stage": q.get("stage"), "kind": str(q.get("kind", "")),
            "message": q.get("message"), "channel": q.get("channel"),
            "t_start": _num(q.get("t_start")), "t_end": _num(q.get("t_end")),
            "fatal": bool(q.get("fatal", False))})
    return out
