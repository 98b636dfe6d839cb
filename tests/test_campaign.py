"""Campaign runner mechanics, with the TEST DOUBLE pipeline of ``test_campaign_doubles``.

Idempotent reruns, crash safety, bad recordings stored as failed, worker deaths,
local process pools.  The real pipeline end to end: ``test_campaign_e2e.py``; Dask
and PostgreSQL: ``test_campaign_backends.py``.
"""

from __future__ import annotations

import json

import pytest
import sqlalchemy as sa

from ident.cli import main
from ident.errors import MillFileError, RecordingError, StoreError
from ident.store import Settings, discover, load_results, open_store, run_campaign
from ident.store import schema as S

from test_campaign_doubles import double_process, make_double_campaign, write_double_recording


@pytest.fixture
def campaign(tmp_path):
    folder = tmp_path / "campaign"
    make_double_campaign(folder, n=6, bad=1)
    return folder


def _run(folder, mill, url, **kw):
    kw.setdefault("workers", 0)
    kw.setdefault("progress", False)
    return run_campaign(folder, mill, url, process=double_process, **kw)


def test_good_stored_bad_failed_with_reason(campaign, mill, tmp_path):
    url = f"sqlite:///{tmp_path}/r.db"
    s = _run(campaign, mill, url)
    assert (s.n_found, s.n_done, s.n_failed, s.n_skipped) == (7, 6, 1, 0)
    assert s.failed[0][0] == "broken0.mcap"
    assert "read: " in s.failed[0][1] and "broken0.mcap" in s.failed[0][1]
    res = load_results(url)
    rec = res["recordings"].set_index("file_name")
    assert rec.loc["broken0.mcap", "status"] == "failed"
    assert rec.loc["broken0.mcap", "error_kind"] == "RecordingError"
    assert rec.loc["broken0.mcap", "stage"] == "read"
    assert "truncated or corrupt MCAP" in rec.loc["broken0.mcap", "error"]
    assert (rec.drop("broken0.mcap")["status"] == "done").all()
    assert rec["versions"].map(lambda v: "ident" in v).all()
    runs = res["runs"]
    assert runs.loc[0, "status"] == "finished" and runs.loc[0, "n_failed"] == 1


def test_rerun_redoes_nothing(campaign, mill, tmp_path):
    url = f"sqlite:///{tmp_path}/r.db"
    _run(campaign, mill, url)
    seen = []
    s = _run(campaign, mill, url, on_stored=lambda f, o: seen.append(f))
    assert seen == [] and (s.n_skipped, s.n_done, s.n_failed) == (7, 0, 0)
    assert [f for f, _ in s.failed] == ["broken0.mcap"]  # still reported (exit code 3)
    with open_store(url) as st:
        assert st.count("recordings") == 7
    # a new recording: only it is processed; a changed one is processed again
    write_double_recording(campaign / "new.mcap", day=40, seed=9)
    write_double_recording(campaign / "rec000.mcap", day=0, seed=42)
    s = _run(campaign, mill, url, on_stored=lambda f, o: seen.append(f))
    assert sorted(seen) == ["new.mcap", "rec000.mcap"] and s.n_skipped == 6
    # other settings: everything again
    s = _run(campaign, mill, url, settings=Settings(family="g4"))
    assert s.n_skipped == 0 and s.n_done == 7


def test_retry_failed(campaign, mill, tmp_path):
    url = f"sqlite:///{tmp_path}/r.db"
    write_double_recording(campaign / "flaky.mcap", day=2, fail_stage="fit")
    s = _run(campaign, mill, url)
    assert s.n_failed == 2
    failed = dict(s.failed)
    assert failed["flaky.mcap"].startswith("fit: solver failed")
    # partial results of a failed recording are kept for the data-quality summary
    res = load_results(url)
    flaky = res["recordings"].set_index("file_name").loc["flaky.mcap"]
    assert flaky["stage"] == "fit" and flaky["n_transients"] == 4
    s = _run(campaign, mill, url, retry_failed=True)
    assert s.n_skipped == 6 and s.n_failed == 2
    with open_store(url) as st:
        assert st.count("recordings") == 8  # replaced, not duplicated


def test_crash_loses_nothing_written(campaign, mill, tmp_path):
    """The parent dies after 3 commits: those 3 are whole; a rerun does only the rest."""
    url = f"sqlite:///{tmp_path}/r.db"
    stored = []

    def die_after_three(name, outcome):
        stored.append(name)
        if len(stored) == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _run(campaign, mill, url, on_stored=die_after_three)
    res = load_results(url)
    assert len(res["recordings"]) == 3
    assert res["runs"].loc[0, "status"] == "interrupted"
    per_rec = res["transients"].groupby("file_name").size()
    for name in stored:
        if res["recordings"].set_index("file_name").loc[name, "status"] == "done":
            assert per_rec[name] == 4
            assert (res["element_results"]["file_name"] == name).sum() == len(mill.elements)
    redo = []
    s = _run(campaign, mill, url, on_stored=lambda f, o: redo.append(f))
    assert s.n_skipped == 3 and sorted(redo + stored) == sorted(x.file_name
                                                                for x in discover(campaign))


def test_half_written_recording_never_visible(campaign, mill, tmp_path, monkeypatch):
    """The database write fails in the middle of the 4th recording's transaction."""
    url = f"sqlite:///{tmp_path}/r.db"
    from ident.store.store import Store

    real = Store._insert_children
    n = {"calls": 0}

    def flaky(self, conn, pk, rows):
        n["calls"] += 1
        if n["calls"] == 4:
            conn.execute(S.transients.insert(), [dict(r, recording_pk=pk)
                                                 for r in rows["transients"]])
            raise sa.exc.OperationalError("INSERT", {}, Exception("disk I/O error"))
        return real(self, conn, pk, rows)

    monkeypatch.setattr(Store, "_insert_children", flaky)
    with pytest.raises(StoreError, match="cannot write to the results store.*disk I/O error"):
        _run(campaign, mill, url)
    with open_store(url) as st:
        assert st.count("recordings") == 3
        with st.engine.connect() as c:
            orphans = c.execute(sa.text("select count(*) from transients where recording_pk "
                                        "not in (select id from recordings)")).scalar_one()
        assert orphans == 0


def test_local_pool_two_workers_and_a_dying_worker(campaign, mill, tmp_path):
    """Real worker processes; one recording kills its worker, the rest are stored."""
    write_double_recording(campaign / "killer.mcap", day=5, crash=True)
    url = f"sqlite:///{tmp_path}/r.db"
    s = _run(campaign, mill, url, workers=2, tasks_per_worker=3)
    assert s.executor == "local:2"
    assert (s.n_done, s.n_failed) == (6, 2)
    err = dict(s.failed)["killer.mcap"]
    assert "worker process died" in err
    rec = load_results(url)["recordings"]
    assert len(set(rec["worker"].dropna())) >= 2  # workers were replaced / several


def test_memory_limit_per_worker(tmp_path, mill):
    folder = tmp_path / "c"
    write_double_recording(folder / "ok.mcap", day=0)
    write_double_recording(folder / "hog.mcap", day=1, alloc_mb=4000)
    s = _run(folder, mill, f"sqlite:///{tmp_path}/r.db", workers=1, memory_limit_mb=1500)
    assert s.n_done == 1 and s.n_failed == 1
    err = dict(s.failed)["hog.mcap"]
    assert "out of memory" in err or "MemoryError" in err


def test_bad_inputs(tmp_path, mill):
    with pytest.raises(RecordingError, match="campaign folder not found"):
        _run(tmp_path / "nope", mill, f"sqlite:///{tmp_path}/r.db")
    with pytest.raises(MillFileError, match="mill file not found"):
        _run(tmp_path, tmp_path / "nope.toml", f"sqlite:///{tmp_path}/r.db")
    with pytest.raises(StoreError, match="Got 'nonsense'"):
        _run(tmp_path, mill, "nonsense")


def test_discovery_groups_csv_devices_and_skips_hidden(tmp_path):
    for name in ("a.mcap", "day1/b.csv", "day1/b.accel.csv", "day1/c.csv", ".hidden/x.mcap",
                 "_tmp.mcap", "notes.txt"):
        p = tmp_path / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(name)
    found = discover(tmp_path)
    assert [s.file_name for s in found] == ["a.mcap", "day1/b.csv", "day1/c.csv"]
    b = found[1]
    assert [p.name for p in b.paths] == ["b.csv", "b.accel.csv"]
    import hashlib
    assert found[0].content_sha256 == hashlib.sha256(b"a.mcap").hexdigest()


def test_summary_json(campaign, mill, tmp_path):
    s = _run(campaign, mill, f"sqlite:///{tmp_path}/r.db")
    d = json.loads(json.dumps(s.to_dict()))
    assert d["found"] == 7 and d["failed"] == 1 and d["failed_recordings"][0]["file"] == \
        "broken0.mcap"


def test_unreadable_and_young_files(tmp_path, mill, monkeypatch):
    import os
    import time

    import ident.store.discovery as D

    folder = tmp_path / "c"
    make_double_campaign(folder, n=2, bad=0)
    write_double_recording(folder / "locked.mcap", day=3)
    real = D.content_hash

    def no_access(paths):
        if paths[0].name == "locked.mcap":
            raise PermissionError(13, "Permission denied", str(paths[0]))
        return real(paths)

    monkeypatch.setattr(D, "content_hash", no_access)
    found = {s.file_name: s for s in discover(folder)}
    assert found["locked.mcap"].content_sha256.startswith("unreadable-")
    assert len(found["locked.mcap"].content_sha256) == 63
    old = time.time() - 3600
    for p in folder.glob("rec*.mcap"):
        os.utime(p, (old, old))
    young = {s.file_name for s in discover(folder, min_age_s=600)}
    assert young == {"rec000.mcap", "rec001.mcap"}


def test_parent_killed_with_sigkill(tmp_path, mill, mill_path):
    """kill -9 of the campaign process mid-run: what was committed is whole, the rest redone."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    folder = tmp_path / "c"
    for i in range(8):
        write_double_recording(folder / f"r{i}.mcap", day=i, seed=i, sleep_s=0.4)
    url = f"sqlite:///{tmp_path}/r.db"
    code = ("import sys; from ident.store import run_campaign; "
            "from test_campaign_doubles import double_process; "
            f"run_campaign({str(folder)!r}, {str(mill_path)!r}, {url!r}, workers=0, "
            "process=double_process, progress=False)")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parent))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    try:
        deadline = time.time() + 120
        while time.time() < deadline:
            try:
                with open_store(url, create=False) as st:
                    if st.count("recordings") >= 3:
                        break
            except StoreError:
                pass
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    with open_store(url) as st, st.engine.connect() as c:
        assert c.execute(sa.text("pragma integrity_check")).scalar_one() == "ok"
        n = st.count("recordings")
        assert 3 <= n < 8
        per = dict(c.execute(sa.text("select recording_pk, count(*) from transients "
                                     "group by recording_pk")).all())
        assert sorted(per.values()) == [4] * n  # every stored recording is whole
        assert c.execute(sa.text("select status from runs")).scalar_one() == "running"
    redo = []
    s = _run(folder, mill, url, on_stored=lambda f, o: redo.append(f))
    assert s.n_skipped == n and len(redo) == 8 - n and s.n_failed == 0


def test_the_cli_campaign_trains_the_mills_model_on_first_use(tmp_path, mill, mill_path,
                                                              monkeypatch, capsys):
    """``ident campaign`` diagnoses by default: no cached model -> ensure_model trains one."""
    import ident.store.campaign as C
    from ident.cli import main
    from ident.diagnose import model_cache_path

    calls = []

    def fake_ensure(m, *, samples, jobs, progress):
        calls.append((m.name, samples, jobs, progress))
        path = model_cache_path(m)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"a model")
        return path

    monkeypatch.setattr(C, "ensure_model", fake_ensure)
    (tmp_path / "empty").mkdir()
    base = ["campaign", str(tmp_path / "empty"), "--mill", str(mill_path), "--workers", "0",
            "--store", f"sqlite:///{tmp_path}/r.db", "--quiet"]
    try:
        assert main(base + ["--no-diagnose"]) == 0
        assert calls == []
        assert main(base + ["--samples", "40", "--jobs", "1"]) == 0
        assert calls == [("hsm-f1", 40, 1, False)]
        assert main(base + ["--samples", "5"]) == 2
        assert "--samples must be at least 10. Got 5" in capsys.readouterr().err
        # the library's run_campaign trains only when asked, and never for a test double
        run_campaign(tmp_path / "empty", mill, f"sqlite:///{tmp_path}/r.db", workers=0,
                     progress=False)
        run_campaign(tmp_path / "empty", mill, f"sqlite:///{tmp_path}/r.db", workers=0,
                     progress=False, process=double_process, train=True)
        assert len(calls) == 1
    finally:
        model_cache_path(mill).unlink(missing_ok=True)


def test_settings_hash_keeps_old_keys_and_sees_new_ones(mill):
    """Settings added later (nuisance, the fit budget) leave the hash of a default
    run as it was, so a stored campaign is not redone; a changed value changes it."""
    from ident.store import Settings, settings_hash
    from ident.store.process import FIT_BUDGET_S

    base = settings_hash(Settings(), mill)
    assert "fit_budget_s" not in Settings().to_dict() and "nuisance" not in Settings().to_dict()
    assert settings_hash(Settings(fit_budget_s=FIT_BUDGET_S), mill) == base
    assert settings_hash(Settings(fit_budget_s=120.0), mill) != base
    assert settings_hash(Settings(nuisance=True), mill) != base


def test_campaign_cli_refuses_a_bad_fit_budget(tmp_path, mill_path):
    assert main(["campaign", str(tmp_path), "--mill", str(mill_path), "--store",
                 f"sqlite:///{tmp_path}/r.db", "--fit-budget", "0", "--quiet"]) == 2
