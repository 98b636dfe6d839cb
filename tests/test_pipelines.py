"""pipelines/: the demo (main job), the daily job and the shipped sample (real pipeline)."""

from __future__ import annotations

import fcntl
import json

import pytest

from ident.store import Settings, load_results, make_sample_campaign, run_campaign


@pytest.fixture(autouse=True)
def _repo_on_path(repo_root, monkeypatch):
    """``pipelines`` is run from the repository root (``python -m pipelines.demo``)."""
    monkeypatch.syspath_prepend(str(repo_root))


@pytest.fixture
def tiny_cached_model(mill):
    """A small wear model of the shipped mill in the (hermetic) cache, removed after: the
    demo diagnoses with the mill's cached model and would otherwise train the full one
    first (about 4 minutes; training on first use is tested in test_diagnose and the
    campaign's e2e test)."""
    from ident.diagnose import model_cache_path, save_model, simulate_library, train_model
    from ident.store import available_stages

    cached = model_cache_path(mill)
    if "diagnose" in available_stages() and not cached.exists():
        lib = simulate_library(mill, n=16, random_state=5)
        save_model(train_model(lib, mill, random_state=0, max_iter=30), cached)
    yield cached
    cached.unlink(missing_ok=True)


def test_demo_end_to_end_and_rerun(tmp_path, capsys, tiny_cached_model):
    from pipelines import demo

    out = tmp_path / "demo"
    args = ["--out", str(out), "--recordings", "2", "--bars", "1", "--days", "10",
            "--workers", "0", "--quiet"]
    assert demo.run(args) == 0
    printed = capsys.readouterr().out
    assert f"Report: {(out / 'report.html').resolve()}" in printed
    summary = json.loads((out / "campaign.json").read_text())
    assert (summary["done"], summary["failed"]) == (2, 2)
    html = (out / "report.html").read_text()
    assert "At a glance" in html and "Failed recordings (2)" in html
    assert demo.run(args) == 0  # the rerun reuses recordings and redoes nothing
    summary = json.loads((out / "campaign.json").read_text())
    assert (summary["skipped"], summary["done"]) == (4, 0)
    assert "reusing the recordings" in capsys.readouterr().err


def test_daily_is_incremental_and_locked(tmp_path, mill, mill_path, capsys):
    from pipelines import daily

    incoming = tmp_path / "incoming"
    make_sample_campaign(incoming, mill, n_recordings=2, bars=1, days=1.0, bearings=False,
                         csv_every=0, n_bad=1, seed=3)
    store = f"sqlite:///{tmp_path}/results.db"
    report = tmp_path / "www" / "report.html"
    args = ["--incoming", str(incoming), "--mill", str(mill_path), "--store", store,
            "--report", str(report), "--archive", str(tmp_path / "archive"), "--workers", "0",
            "--min-age-s", "0", "--no-fit", "--no-diagnose"]
    # the job's mechanics (without --no-diagnose it trained the full wear model first: 200 s);
    # test_demo fits and diagnoses for real, test_diagnose trains on first use
    assert daily.run(args) == 3  # the malformed file is stored as failed and reported
    assert report.exists() and len(list((tmp_path / "archive").glob("report-*.html"))) == 1
    # the next day: one new recording, only it is processed
    make_sample_campaign(tmp_path / "next", mill, n_recordings=1, bars=1, bearings=False,
                         csv_every=0, n_bad=0, seed=4, t0_ns=1_767_225_600_000_000_000 + 2 *
                         86_400 * 10**9)
    new = next((tmp_path / "next").rglob("*.mcap"))
    new.rename(incoming / "new_day.mcap")
    assert daily.run(args) == 3
    summary = json.loads(report.with_suffix(".campaign.json").read_text())
    assert (summary["done"], summary["skipped"]) == (1, 3)
    # a run that finds the previous one still going does nothing
    with open(report.with_name(report.name + ".lock"), "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        assert daily.run(args) == 0
    assert "nothing to do" in capsys.readouterr().err


def test_shipped_sample_campaign(repo_root, mill, tmp_path):
    folder = repo_root / "data" / "samples" / "hsm-f1"
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    assert size < 700 * 1024
    s = run_campaign(folder, mill, f"sqlite:///{tmp_path}/s.db", workers=0, progress=False,
                     settings=Settings(fit=False))  # notebook 03 fits it for real
    assert (s.n_done, s.n_failed) == (4, 2)
    truth = json.loads((folder / "TRUTH.json").read_text())
    rec = load_results(f"sqlite:///{tmp_path}/s.db")["recordings"].set_index("file_name")
    for name, t in truth.items():
        assert rec.loc[name, "t0_ns"] == t["t0_ns"]


@pytest.mark.parametrize("unit", ["ident-daily.service", "ident-daily.timer"])
def test_systemd_units_are_well_formed(repo_root, unit):
    import configparser

    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.read(repo_root / "pipelines" / "systemd" / unit)
    if unit.endswith(".service"):
        assert "-m pipelines.daily" in cp["Service"]["ExecStart"]
        assert cp["Service"]["SuccessExitStatus"] == "3"
    else:
        assert cp["Timer"]["OnCalendar"] and cp["Install"]["WantedBy"] == "timers.target"
