"""Campaigns on a Dask LocalCluster and into a real PostgreSQL server.

The PostgreSQL fixture starts a throwaway cluster (``initdb`` + ``pg_ctl`` from
``/usr/lib/postgresql/*/bin`` or PATH) on a free localhost port, as the
``postgres`` user when run as root; without the server binaries or the psycopg
driver the tests are skipped with the reason (``pytest -rs`` shows it).  CI
installs them with ``apt-get install -y postgresql`` (see pipelines/README.md).
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from ident.report import build_report
from ident.store import Settings, load_results, make_sample_campaign, open_store, run_campaign
from ident.store.campaign import CampaignError

from test_campaign_doubles import double_process, make_double_campaign


# ---- Dask -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dask_cluster():
    distributed = pytest.importorskip("distributed", reason="dask.distributed not installed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       memory_limit="1GiB", dashboard_address=None)
    try:
        yield cluster
    finally:
        cluster.close()


def test_dask_local_cluster_real_pipeline(dask_cluster, mill, tmp_path):
    sample = make_sample_campaign(tmp_path / "c", mill, n_recordings=2, bars=1, days=3.0,
                                  bearings=False, csv_every=0, n_bad=1, seed=11)
    url = f"sqlite:///{tmp_path}/r.db"
    # the real per-recording pipeline on dask workers (read, quality, segments, TAF); the fit
    # stage is off here because its cost is the fit's, tested in test_campaign_e2e
    quick = Settings(fit=False, diagnose=False)
    s = run_campaign(sample.folder, mill, url, scheduler=dask_cluster.scheduler_address,
                     progress=False, settings=quick)
    assert s.executor.startswith("dask:tcp://")
    assert (s.n_done, s.n_failed) == (2, 1)
    assert "truncated.mcap" in s.failed[0][0]
    rec = load_results(url)["recordings"]
    assert rec["worker"].notna().all()
    again = run_campaign(sample.folder, mill, url, scheduler=dask_cluster.scheduler_address,
                         progress=False, settings=quick)
    assert again.n_skipped == 3 and again.n_done == 0


def test_dask_worker_death_is_a_failed_recording(dask_cluster, mill, tmp_path):
    from test_campaign_doubles import write_double_recording

    folder = tmp_path / "c"
    make_double_campaign(folder, n=3, bad=0)
    write_double_recording(folder / "killer.mcap", day=1, crash=True)
    import dask
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        s = run_campaign(folder, mill, f"sqlite:///{tmp_path}/r.db",
                         scheduler=dask_cluster.scheduler_address, process=double_process,
                         progress=False)
    assert s.n_done == 3 and s.n_failed == 1
    assert dict(s.failed)["killer.mcap"].startswith("worker: ")


def test_unreachable_scheduler(tmp_path, mill):
    import dask
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    folder = tmp_path / "c"
    make_double_campaign(folder, n=1, bad=0)
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        with pytest.raises(CampaignError, match=f"cannot reach the Dask scheduler at "
                                                f"'tcp://127.0.0.1:{port}'"):
            run_campaign(folder, mill, f"sqlite:///{tmp_path}/r.db",
                         scheduler=f"tcp://127.0.0.1:{port}", process=double_process,
                         progress=False)


# ---- PostgreSQL -----------------------------------------------------------------------
def _pg_bin(name: str) -> str | None:
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    return found[-1] if found else shutil.which(name)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def postgres_url():
    pytest.importorskip("psycopg", reason="psycopg (v3) not installed: pip install "
                                          "'psycopg[binary]'")
    initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
    if not initdb or not pg_ctl:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) not found; install them "
                    "with: apt-get install -y postgresql")
    prefix: list[str] = []
    user = None
    if os.geteuid() == 0:  # the server refuses to run as root
        for candidate in ("postgres", "nobody"):
            try:
                user = pwd.getpwnam(candidate)
                break
            except KeyError:
                continue
        if user is None or not shutil.which("runuser"):
            pytest.skip("running as root without a 'postgres' user and runuser to start "
                        "PostgreSQL")
        prefix = ["runuser", "-u", user.pw_name, "--"]
    base = Path(tempfile.mkdtemp(prefix="ident-pg-"))
    data = base / "data"
    os.chmod(base, 0o755)
    if user is not None:
        os.chown(base, user.pw_uid, user.pw_gid)
    port = _free_port()
    env = dict(os.environ, LC_ALL="C")

    def run(args: list[str]) -> subprocess.CompletedProcess:
        return subprocess.run(prefix + args, capture_output=True, text=True, env=env,
                              timeout=120)

    r = run([initdb, "-D", str(data), "-U", "ident", "--auth=trust", "-E", "UTF8"])
    if r.returncode != 0:
        shutil.rmtree(base, ignore_errors=True)
        pytest.skip(f"initdb failed: {r.stderr.strip()[-300:]}")
    r = run([pg_ctl, "-D", str(data), "-l", str(base / "log"), "-w", "-t", "60", "-o",
             f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off", "start"])
    if r.returncode != 0:
        log = (base / "log").read_text()[-400:] if (base / "log").exists() else ""
        shutil.rmtree(base, ignore_errors=True)
        pytest.skip(f"PostgreSQL did not start: {r.stderr.strip()[-200:]} {log}")
    try:
        yield f"postgresql://ident@127.0.0.1:{port}/postgres"  # psycopg 3 by default
    finally:
        run([pg_ctl, "-D", str(data), "-m", "immediate", "-w", "stop"])
        shutil.rmtree(base, ignore_errors=True)


def test_postgresql_store(postgres_url, mill, tmp_path):
    folder = tmp_path / "c"
    make_double_campaign(folder, n=5, bad=1)
    s = run_campaign(folder, mill, postgres_url, workers=0, process=double_process,
                     progress=False)
    assert (s.n_done, s.n_failed) == (5, 1)
    assert s.store.startswith("postgresql+psycopg://ident@127.0.0.1:")
    again = run_campaign(folder, mill, postgres_url, workers=0, process=double_process,
                         progress=False)
    assert again.n_skipped == 6 and again.n_done == 0
    res = load_results(postgres_url)
    assert len(res["recordings"]) == 6 and len(res["element_results"]) == 5 * 6
    assert res["fits"]["result"].map(lambda d: d["family"]).eq("g3").all()
    r = build_report(postgres_url, tmp_path / "r.html")
    assert r.n_failed == 1 and "Failed recordings (1)" in r.path.read_text()


def test_postgresql_transaction_rollback(postgres_url, mill, tmp_path, monkeypatch):
    from ident.store.store import Store

    folder = tmp_path / "c"
    make_double_campaign(folder, n=2, bad=0)
    url = postgres_url
    with open_store(url) as st:
        before = st.count("recordings"), st.count("transients")

    def boom(self, conn, pk, rows):
        raise RuntimeError("worker crash during the write")

    monkeypatch.setattr(Store, "_insert_children", boom)
    with pytest.raises(RuntimeError):
        run_campaign(folder, mill, url, workers=0, process=double_process, progress=False,
                     settings=__import__("ident.store", fromlist=["Settings"]).Settings(
                         family="g2"))
    with open_store(url) as st:
        assert (st.count("recordings"), st.count("transients")) == before


def test_postgresql_bad_server(tmp_path):
    from ident.errors import StoreError
    with pytest.raises(StoreError, match="cannot open the results store postgresql"):
        open_store(f"postgresql+psycopg://ident@127.0.0.1:{_free_port()}/postgres"
                   "?connect_timeout=2")
    time.sleep(0)
