"""The results store: URLs, one transaction per recording, keys, loading into pandas."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import pytest
import sqlalchemy as sa

from ident.errors import StoreError
from ident.store import RecordingKey, Settings, load_results, open_store
from ident.store import schema as S
from ident.store.store import normalize_url, outcome_rows

from test_campaign_doubles import double_process, write_double_recording


@pytest.fixture
def outcome(tmp_path, mill):
    p = write_double_recording(tmp_path / "r.mcap", day=3, gaps={"C46": 0.005}, seed=1)
    return double_process(p, mill, Settings())


def _write(store, mill, outcome, name="r.mcap", sha="a" * 64, shash="s" * 64, **kw):
    store.register_mill(mill, Path(mill.source).read_text())
    run = store.start_run(directory="/x", mill=mill, settings_hash=shash, settings={},
                          executor="inline", host="h", versions={}, n_found=1, n_skipped=0)
    return store.write_outcome(run, RecordingKey(name, sha, shash), outcome, mill=mill,
                               files=[name], size_bytes=10, **kw)


def test_bad_urls_are_store_errors(tmp_path):
    with pytest.raises(StoreError, match="must be an SQLAlchemy database URL.*Got 'not a url'"):
        open_store("not a url")
    with pytest.raises(StoreError, match="results store not found: .*missing.db"):
        open_store(f"sqlite:///{tmp_path}/missing.db", create=False)
    with pytest.raises(StoreError, match="no database driver"):
        open_store("mysql+nosuchdriver://u@h/db")
    assert normalize_url("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"


def test_foreign_sqlite_file_is_refused(tmp_path):
    db = tmp_path / "other.db"
    sqlite3.connect(db).execute("create table x (a int)").connection.commit()
    with pytest.raises(StoreError, match="not an ident results store"):
        open_store(f"sqlite:///{db}", create=False)


def test_a_reader_does_not_write_the_version_of_a_store_being_created(tmp_path):
    """A poller (``create=False``) racing the campaign that creates the store must not
    insert the schema version itself: the creator's insert then failed UNIQUE (CI)."""
    url = f"sqlite:///{tmp_path}/s.db"
    S.metadata.create_all(sa.create_engine(url))  # tables made, version not yet written
    with pytest.raises(StoreError, match="being created"):
        open_store(url, create=False)
    with sa.create_engine(url).connect() as c:
        assert c.execute(sa.select(sa.func.count()).select_from(S.schema_info)).scalar_one() == 0
    open_store(url).close()  # the creator still succeeds
    with sa.create_engine(url).begin() as c:  # and a second creator reads its version
        assert c.execute(sa.select(S.schema_info.c.value)).scalar_one() == str(S.SCHEMA_VERSION)
    open_store(url).close()


def test_schema_version_mismatch(tmp_path):
    url = f"sqlite:///{tmp_path}/s.db"
    open_store(url).close()
    with sa.create_engine(url).begin() as c:
        c.execute(S.schema_info.update().values(value="999"))
    with pytest.raises(StoreError, match="schema version 999; this ident reads version 2"):
        open_store(url)


def test_a_schema_1_store_is_migrated_keeping_its_rows(tmp_path, mill, outcome):
    """Schema 1 had no verdict columns in ``diagnoses``: they are added, every row kept."""
    db = tmp_path / "old.db"
    with open_store(f"sqlite:///{db}") as st:
        assert _write(st, mill, outcome)
        n_diag = st.count("diagnoses")
    con = sqlite3.connect(db)
    for col in ("source", "value_ci_lo", "value_ci_hi", "uncertain", "reason"):
        con.execute(f"ALTER TABLE diagnoses DROP COLUMN {col}")
    con.execute("UPDATE schema_info SET value = '1' WHERE key = 'schema_version'")
    con.commit()
    con.close()
    with open_store(f"sqlite:///{db}") as st:
        assert st.count("diagnoses") == n_diag > 0 and st.count("recordings") == 1
        assert _write(st, mill, outcome, sha="b" * 64)  # new rows fill the new columns
    with sa.create_engine(f"sqlite:///{db}").connect() as c:
        assert c.execute(sa.select(S.schema_info.c.value)).scalar() == "2"
        cols = {r[1] for r in c.execute(sa.text("PRAGMA table_info(diagnoses)"))}
    assert {"source", "value_ci_lo", "reason"} <= cols
    d = load_results(f"sqlite:///{db}", latest_only=False)["diagnoses"]
    old, new = d[d["source"].isna()], d[d["source"].notna()]
    assert len(old) == len(new) == n_diag  # the old rows: no source (schema 1)
    open_store(f"sqlite:///{db}").close()  # a second open finds nothing to migrate


def test_verdict_rows(mill):
    from ident.store.store import _verdict_rows

    diag = {"elements": {"C46": {"state": "critical", "probability": 0.97, "gap": 9e-3,
                                 "gap_ci95": [8.7e-3, 9.3e-3], "source": "fit",
                                 "uncertain": False},
                         "C23": {"state": "good", "probability": 0.7, "gap": 2e-3,
                                 "reason": "interval wider than the gap"}},
            "bearings": {"B23": {"state": "worn", "probability": 0.8, "clearance": 1.2e-3,
                                 "clearance_ci95": [1.0e-3, 1.4e-3], "uncertain": True}}}
    rows = {r["target"]: r for r in _verdict_rows(diag)}
    assert rows["C46"]["source"] == "fit" and rows["C46"]["value_ci_hi"] == 9.3e-3
    assert rows["C46"]["clearance"] is None and rows["C46"]["uncertain"] is False
    assert rows["C23"]["source"] == "diagnosis"  # a JSON without a source came from the model
    assert rows["C23"]["reason"] == "interval wider than the gap"
    assert rows["C23"]["value_ci_lo"] is None and rows["C23"]["uncertain"] is None
    assert rows["B23"]["kind"] == "bearing" and rows["B23"]["gap"] is None
    assert rows["B23"]["clearance"] == 1.2e-3 and rows["B23"]["value_ci_lo"] == 1.0e-3


def test_roundtrip_every_table(tmp_path, mill, outcome):
    url = f"sqlite:///{tmp_path}/sub/dir/s.db"  # folders are created
    with open_store(url) as st:
        assert _write(st, mill, outcome)
    res = load_results(url)
    rec = res["recordings"]
    assert len(rec) == 1 and rec.loc[0, "status"] == "done"
    assert rec.loc[0, "mill_sha256"] == mill.sha256 and rec.loc[0, "recording_id"] == "r"
    assert rec.loc[0, "t0"].isoformat().startswith("2026-01-04")
    assert res["mills"].loc[0, "text"].startswith("# Hot strip mill")
    assert len(res["transients"]) == 4 and set(res["transients"]["kind"]) == {"bite", "release"}
    assert len(res["element_results"]) == len(mill.elements)
    c46 = res["element_results"].set_index("element").loc["C46"]
    assert c46["gap_ci_lo"] < c46["gap"] < c46["gap_ci_hi"]
    assert c46["params"] == {"a0": 1.0e7, "sigma": 900.0}
    assert c46["gap_mm"] == pytest.approx(mill.element("C46").gap_mm(c46["gap"]))
    assert res["fits"].loc[0, "solver_status"] == "Solve_Succeeded"
    assert res["fits"].loc[0, "result"]["family"] == "g3"
    assert set(res["diagnoses"]["kind"]) == {"element", "bearing"}
    assert set(res["features"]["name"]) == {"frequencies_hz", "amplitude_ratio",
                                            "phase_shift_deg"}
    assert res["quality_issues"].loc[0, "kind"] == "dropout"
    assert len(res["taf"]) == 8
    for name in ("transients", "taf", "fits"):  # trends need no join
        assert {"file_name", "t0", "mill_name"} <= set(res[name].columns)


def test_one_transaction_per_recording(tmp_path, mill, outcome, monkeypatch):
    """A failure after the recording row and some children leaves nothing behind."""
    url = f"sqlite:///{tmp_path}/s.db"
    st = open_store(url)
    calls = {"n": 0}
    real = st._insert_children

    def boom(conn, pk, rows):
        conn.execute(S.transients.insert(), [dict(r, recording_pk=pk)
                                             for r in rows["transients"]])
        calls["n"] += 1
        raise RuntimeError("power cut")

    monkeypatch.setattr(st, "_insert_children", boom)
    with pytest.raises(RuntimeError, match="power cut"):
        _write(st, mill, outcome)
    assert calls["n"] == 1
    assert st.count("recordings") == 0 and st.count("transients") == 0
    monkeypatch.setattr(st, "_insert_children", real)
    assert _write(st, mill, outcome)
    assert st.count("recordings") == 1 and st.count("transients") == 4
    st.close()


def test_key_is_unique_and_replace(tmp_path, mill, outcome):
    with open_store(f"sqlite:///{tmp_path}/s.db") as st:
        assert _write(st, mill, outcome)
        assert not _write(st, mill, outcome)  # same key: not written twice
        assert st.count("recordings") == 1
        assert _write(st, mill, outcome, sha="b" * 64)  # new content: a new row
        assert _write(st, mill, outcome, replace=True)  # retry replaces, children too
        assert st.count("recordings") == 2 and st.count("transients") == 8
        assert st.stored_keys("s" * 64) == {("r.mcap", "a" * 64): "done",
                                             ("r.mcap", "b" * 64): "done"}


def test_rows_tolerate_non_finite_and_extra_keys(outcome):
    seg = dict(outcome.segments[0], t_end=math.nan, confidence=0.7)
    fit = dict(outcome.fit, metrics={"nrmse": math.inf})
    from dataclasses import replace
    rows = outcome_rows(replace(outcome, segments=(seg,), fit=fit))
    assert rows["transients"][0]["t_end"] is None
    assert rows["transients"][0]["extra"] == {"confidence": 0.7}
    assert rows["fits"][0]["nrmse"] is None and rows["fits"][0]["nrmse_linear"] is None


def test_latest_only(tmp_path, mill, outcome):
    url = f"sqlite:///{tmp_path}/s.db"
    with open_store(url) as st:
        _write(st, mill, outcome, sha="a" * 64)
        _write(st, mill, outcome, sha="b" * 64)
    assert len(load_results(url)["recordings"]) == 1
    assert len(load_results(url, latest_only=False)["recordings"]) == 2
    assert load_results(url)["recordings"].loc[0, "content_sha256"] == "b" * 64
    assert len(load_results(url, mill="other")["recordings"]) == 0
