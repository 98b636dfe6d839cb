"""The results store's tables (SQLAlchemy Core), one row per stored fact.

A campaign writes one :data:`recordings` row per recording file and, in the same
transaction, the rows that hang off it: its transients, the measured TAF per
transient and element, the fits (solver status and metrics), the identified gaps
per element, the wear diagnoses, the spectral features and the data-quality
findings.  ``runs`` logs each ``ident campaign`` call and ``mills`` keeps every
mill file a result was computed with, so that a report can read the limits
without the file.

Keys: a recording is identified by ``(file_name, content_sha256, settings_hash)``
(unique): its path relative to the campaign folder, the SHA-256 of its bytes and
the hash of the processing settings together with the mill description.

``diagnoses`` holds one wear verdict per element and bearing of a recording
(:mod:`ident.diagnose.verdict`): the state, its probability and its ``source``,
``fit`` (the fit identified the gap) or ``diagnosis`` (the trained model).  A
transient-level row carries ``transient_idx`` (the index of the transient in the
recording, 0-based); ``NULL`` there means the row describes the whole recording
(e.g. one fit over all its transients).

Units are those of the JSON contracts (``../shared/spec/cli.md``): SI, angles in
rad reduced to the motor shaft, torques in N*m reduced to the motor shaft, times
in seconds from the recording's start; ``t0_ns`` is the recording's absolute
start in ns since the Unix epoch.
"""

from __future__ import annotations

from sqlalchemy import (JSON, BigInteger, Boolean, Column, DateTime, Float, ForeignKey, Index,
                        Integer, MetaData, String, Table, Text, UniqueConstraint)

__all__ = ["SCHEMA_VERSION", "metadata", "schema_info", "mills", "runs", "recordings",
           "transients", "taf", "fits", "element_results", "diagnoses", "features",
           "quality_issues", "CHILD_TABLES"]

#: Bumped whenever a table changes; :func:`ident.store.open_store` migrates a store of an
#: older version (adding the new columns, every row kept) and refuses a newer one.
#: 1: the first; 2: ``diagnoses`` holds the wear verdict (``source``, interval, reason).
SCHEMA_VERSION = 2

metadata = MetaData()

schema_info = Table(
    "schema_info", metadata,
    Column("key", String(64), primary_key=True),
    Column("value", String(256), nullable=False),
)

mills = Table(
    "mills", metadata,
    Column("sha256", String(64), primary_key=True, comment="SHA-256 of the mill file's text"),
    Column("name", String(128), nullable=False),
    Column("content_hash", String(64), nullable=False,
           comment="hash of the description's values (Mill.content_hash)"),
    Column("text", Text, nullable=False, comment="the mill file (TOML)"),
    Column("first_seen", DateTime(timezone=True), nullable=False),
)

runs = Table(
    "runs", metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("started_at", DateTime(timezone=True), nullable=False),
    Column("finished_at", DateTime(timezone=True)),
    Column("status", String(16), nullable=False, comment="running | finished | interrupted"),
    Column("directory", Text, nullable=False),
    Column("mill_name", String(128), nullable=False),
    Column("mill_sha256", String(64), nullable=False),
    Column("settings_hash", String(64), nullable=False),
    Column("settings", JSON, nullable=False),
    Column("executor", String(256), nullable=False, comment="local:N workers | dask:ADDR"),
    Column("host", String(256)),
    Column("versions", JSON),
    Column("n_found", Integer),
    Column("n_skipped", Integer),
    Column("n_done", Integer),
    Column("n_failed", Integer),
)

recordings = Table(
    "recordings", metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("run_id", Integer, ForeignKey("runs.id"), nullable=False),
    Column("file_name", String(1024), nullable=False,
           comment="path relative to the campaign folder, '/'-separated"),
    Column("content_sha256", String(64), nullable=False),
    Column("size_bytes", BigInteger, nullable=False),
    Column("files", JSON, nullable=False, comment="member files (CSV siblings of one recording)"),
    Column("settings_hash", String(64), nullable=False),
    Column("mill_name", String(128), nullable=False),
    Column("mill_sha256", String(64), ForeignKey("mills.sha256"), nullable=False),
    Column("status", String(8), nullable=False, comment="done | failed"),
    Column("error", Text, comment="why it failed: stage, error type and message"),
    Column("error_kind", String(64), comment="error class name, e.g. RecordingError"),
    Column("stage", String(16), comment="stage that failed: read | segment | fit | diagnose"),
    Column("recording_id", String(256), comment="recording_id of the file's metadata"),
    Column("metadata", JSON, comment="the recording's metadata (mill, stand, campaign, ...)"),
    Column("t0_ns", BigInteger, comment="absolute start, ns since the Unix epoch"),
    Column("duration_s", Float),
    Column("n_transients", Integer),
    Column("versions", JSON, comment="ident and library versions that computed the row"),
    Column("started_at", DateTime(timezone=True)),
    Column("finished_at", DateTime(timezone=True)),
    Column("elapsed_s", Float, comment="processing wall time in the worker, s"),
    Column("worker", String(256)),
    UniqueConstraint("file_name", "content_sha256", "settings_hash", name="uq_recording_key"),
)
Index("ix_recordings_mill_t0", recordings.c.mill_name, recordings.c.t0_ns)


def _child(name: str, *columns: Column) -> Table:
    """A table of rows that belong to one recording (deleted with it)."""
    return Table(
        name, metadata,
        Column("id", Integer, primary_key=True, autoincrement=True),
        Column("recording_pk", Integer, ForeignKey("recordings.id", ondelete="CASCADE"),
               nullable=False, index=True),
        Column("transient_idx", Integer, comment="transient index; NULL = whole recording"),
        *columns,
    )


transients = _child(
    "transients",
    Column("kind", String(16), nullable=False, comment="bite | release"),
    Column("t_start", Float), Column("t_step", Float), Column("t_end", Float),
    Column("static_torque", Float, comment="N*m reduced to the motor shaft"),
    Column("step", Float, comment="N*m reduced, negative for a release"),
    Column("extra", JSON, comment="further segment fields"),
)

taf = _child(
    "taf",
    Column("element", String(64), nullable=False),
    Column("channel", String(128), nullable=False),
    Column("static_torque", Float, comment="rolling level, N*m reduced to the motor shaft"),
    Column("peak_torque", Float, comment="largest torque after the bite, N*m reduced"),
    Column("taf", Float, comment="peak_torque / static_torque (seed section 1.1)"),
)

fits = _child(
    "fits",
    Column("family", String(32)),
    Column("nrmse", Float), Column("nrmse_linear", Float),
    Column("solver_status", String(128)),
    Column("solver_iterations", Integer),
    Column("solver_seconds", Float),
    Column("result", JSON, comment="the whole fit JSON (cli.md)"),
)

element_results = _child(
    "element_results",
    Column("element", String(64), nullable=False),
    Column("family", String(32)),
    Column("gap", Float, comment="rad reduced"),
    Column("gap_ci_lo", Float), Column("gap_ci_hi", Float),
    Column("gap_open", Float, comment="rad reduced"),
    Column("gap_mm", Float),
    Column("params", JSON, comment="smoothing parameters of the family"),
    Column("identifiable", Boolean),
)

diagnoses = _child(
    "diagnoses",
    Column("kind", String(8), nullable=False, comment="element | bearing"),
    Column("target", String(64), nullable=False, comment="element or bearing id"),
    Column("state", String(16), comment="good | worn | critical"),
    Column("probability", Float),
    Column("gap", Float, comment="rad reduced (elements)"),
    Column("clearance", Float, comment="m (bearings)"),
    # schema 2: the verdict (ident.diagnose.verdict); NULL source in rows of schema 1
    Column("source", String(16), comment="fit | diagnosis: where the state comes from"),
    Column("value_ci_lo", Float, comment="95 % interval of gap (rad) or clearance (m)"),
    Column("value_ci_hi", Float),
    Column("uncertain", Boolean),
    Column("reason", Text, comment="why an element's verdict is not the fit's"),
)

features = _child(
    "features",
    Column("name", String(64), nullable=False,
           comment="feature list name, e.g. frequencies_hz, amplitude_ratio, phase_shift_deg"),
    Column("idx", Integer, nullable=False, comment="position in the list (the mode)"),
    Column("value", Float),
)

quality_issues = _child(
    "quality_issues",
    Column("stage", String(16)),
    Column("kind", String(64), nullable=False),
    Column("message", Text),
    Column("channel", String(128)),
    Column("t_start", Float), Column("t_end", Float),
    Column("fatal", Boolean),
)

#: Tables whose rows belong to one recording, in insertion order.
CHILD_TABLES: tuple[Table, ...] = (transients, taf, fits, element_results, diagnoses, features,
                                   quality_issues)
