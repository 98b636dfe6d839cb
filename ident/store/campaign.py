"""Run a campaign: every recording under a folder, processed in parallel, into a store.

:func:`run_campaign` finds the recordings (:mod:`ident.store.discovery`), skips
those already stored with the same content and settings, sends the rest to worker
processes (a local process pool on all cores, or a Dask cluster), and writes each
outcome as it arrives, one transaction per recording, from this process only.

Failure model
-------------
* A recording that fails in any stage is stored as ``failed`` with its reason;
  the rest go on.
* A worker process that dies (killed, out of memory, a crash in native code)
  breaks a local pool: the pool is restarted and the recordings that were in
  flight are retried one at a time, so that the one that kills its worker is
  found and stored as failed.  On Dask the scheduler retries a task whose worker
  died and gives up after its ``allowed-failures``; that too is stored as failed.
* The parent crashing loses nothing already written: each recording is committed
  on its own, and a rerun skips it.

Memory is bounded per worker: one recording at a time per worker process, at most
two recordings queued per worker, local workers replaced after
``tasks_per_worker`` recordings (and optionally limited to ``memory_limit_mb`` of
address space); Dask workers by the cluster's ``memory_limit``.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import socket
import sys
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from ..description import Mill
from ..errors import IdentError, MillFileError, ModelArtifactError, StoreError
from ..io.millfile import load_mill
from .discovery import RecordingSource, discover
from .outcome import RecordingOutcome
from .process import (DEFAULT_LIBRARY_SAMPLES, ProcessFn, Settings, available_stages,
                      describe_error, ensure_model, library_versions, model_path,
                      process_recording, settings_hash)
from .refit import Refit, neighbour_starts
from .store import RecordingKey, Store, open_store

__all__ = ["run_campaign", "CampaignSummary", "CampaignError", "default_workers"]


class CampaignError(IdentError, RuntimeError):
    """A campaign cannot run: e.g. its Dask scheduler cannot be reached."""


@dataclass(frozen=True)
class CampaignSummary:
    """What a campaign run did.

    Attributes
    ----------
    run_id : int
        Row of the ``runs`` table.
    store : str
        Store URL (without password).
    n_found : int
        Recordings under the folder.
    n_skipped : int
        Already stored with the same content and settings (not processed again).
    n_done, n_failed : int
        Processed by this run, successfully / as failed.
    failed : tuple of (str, str)
        ``(file_name, error)`` of every recording under the folder stored as failed,
        by this run or an earlier one.
    elapsed_s : float
        Wall time, s.
    executor : str
        ``local:N`` (N worker processes), ``inline`` or ``dask:ADDR``.
    n_refit : int
        Recordings this run refitted from a neighbour (:mod:`ident.store.refit`),
        not counted in ``n_done``.
    """

    run_id: int
    store: str
    n_found: int
    n_skipped: int
    n_done: int
    n_failed: int
    failed: tuple[tuple[str, str], ...] = ()
    elapsed_s: float = 0.0
    executor: str = ""
    n_refit: int = 0

    @property
    def throughput_per_min(self) -> float:
        """Recordings processed per minute by this run."""
        n = self.n_done + self.n_failed
        return 60.0 * n / self.elapsed_s if self.elapsed_s > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "store": self.store, "found": self.n_found,
                "skipped": self.n_skipped, "done": self.n_done, "failed": self.n_failed,
                "failed_recordings": [{"file": f, "error": e} for f, e in self.failed],
                "refitted": self.n_refit,
                "elapsed_s": round(self.elapsed_s, 3), "executor": self.executor,
                "recordings_per_min": round(self.throughput_per_min, 2)}


def default_workers() -> int:
    """Worker processes by default: every core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


# ---- work unit (runs in the workers) ------------------------------------------------
def _work(process: ProcessFn, path: str, mill: Mill, settings: Settings) -> RecordingOutcome:
    return process(Path(path), mill, settings)


def _init_worker(memory_limit_mb: int | None) -> None:
    """Worker start: one BLAS/OpenMP thread; optionally cap the address space."""
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass
    if memory_limit_mb:
        import resource

        lim = int(memory_limit_mb) * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))


@dataclass
class _Job:
    source: RecordingSource
    replace: bool = False
    alone: bool = False
    settings: Settings | None = None  # a refit's (the run's otherwise)
    refit: tuple[Refit, str] | None = None  # what it refits, and its settings hash


# ---- executors ----------------------------------------------------------------------
class _Inline:
    """Run in this process (``workers=0``): no isolation, for debugging."""

    name = "inline"
    capacity = 1

    def __init__(self, process: ProcessFn) -> None:
        self.process = process

    def submit(self, path: str, mill: Mill, settings: Settings) -> cf.Future:
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(_work(self.process, path, mill, settings))
        except Exception as exc:  # noqa: BLE001 - reported like a worker's failure
            fut.set_exception(exc)
        return fut

    def wait(self, futs) -> set:
        return set(futs)

    def restart(self) -> None:  # pragma: no cover - nothing to restart
        pass

    def close(self, *, cancel: bool = False) -> None:
        pass


#: Modules a local worker needs; the fork server imports them once for all workers.
_WORKER_PRELOAD = ("ident.store.campaign", "ident.store.taf", "ident.io.readers",
                   "ident.segment", "ident.fit", "ident.features", "ident.diagnose")


def _mp_context() -> multiprocessing.context.BaseContext:
    """Start workers by forking a server that has imported ident once (Linux); else spawn.

    ``fork`` itself cannot be used with worker replacement (``max_tasks_per_child``)
    and is unsafe in a threaded parent; the fork server is a clean single-threaded
    process, so a worker starts in milliseconds instead of re-importing everything
    (a stage that fails to import is left out of the preload and fails in the worker).
    """
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(list(_WORKER_PRELOAD))
        return ctx
    return multiprocessing.get_context("spawn")  # pragma: no cover - not Linux


class _LocalPool:
    """Worker processes on this machine (forked from a preloaded server, or spawned)."""

    def __init__(self, process: ProcessFn, workers: int, *, tasks_per_worker: int,
                 memory_limit_mb: int | None) -> None:
        self.process = process
        self.workers = workers
        self.capacity = 2 * workers
        self.name = f"local:{workers}"
        self._kw = dict(max_workers=workers, mp_context=_mp_context(),
                        max_tasks_per_child=tasks_per_worker, initializer=_init_worker,
                        initargs=(memory_limit_mb,))
        self.pool = cf.ProcessPoolExecutor(**self._kw)

    def submit(self, path: str, mill: Mill, settings: Settings) -> cf.Future:
        return self.pool.submit(_work, self.process, path, mill, settings)

    def wait(self, futs) -> set:
        done, _ = cf.wait(futs, return_when=cf.FIRST_COMPLETED)
        return done

    def restart(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.pool = cf.ProcessPoolExecutor(**self._kw)

    def close(self, *, cancel: bool = False) -> None:
        self.pool.shutdown(wait=not cancel, cancel_futures=cancel)


class _Dask:
    """The same work units on a Dask distributed cluster."""

    def __init__(self, process: ProcessFn, address: str) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise CampaignError("--scheduler needs dask.distributed: pip install "
                                "'dask[distributed]'") from None
        try:
            self.client = Client(address, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise CampaignError(f"cannot reach the Dask scheduler at {address!r}: {exc}") from None
        self.process = process
        threads = sum(self.client.nthreads().values()) or 1
        self.capacity = 2 * threads
        self.name = f"dask:{address}"

    def submit(self, path: str, mill: Mill, settings: Settings):
        return self.client.submit(_work, self.process, path, mill, settings, pure=False)

    def wait(self, futs) -> set:
        from distributed import wait

        with self.client.as_current():
            done, _ = wait(list(futs), return_when="FIRST_COMPLETED")
        return set(done)

    def restart(self) -> None:  # pragma: no cover - the scheduler recovers by itself
        pass

    def close(self, *, cancel: bool = False) -> None:
        self.client.close()


def _make_executor(process: ProcessFn, workers: int | None, scheduler: str | None, *,
                   tasks_per_worker: int, memory_limit_mb: int | None):
    if scheduler:
        return _Dask(process, scheduler)
    n = default_workers() if workers is None else int(workers)
    if n < 0:
        raise CampaignError(f"workers must be 0 (in this process) or more. Got {n}")
    if n == 0:
        return _Inline(process)
    return _LocalPool(process, n, tasks_per_worker=tasks_per_worker,
                      memory_limit_mb=memory_limit_mb)


def _worker_died(job: _Job, exc: BaseException) -> RecordingOutcome:
    return RecordingOutcome(
        status="failed", stage="worker", error_kind=type(exc).__name__,
        error=(f"worker: the worker process died while processing {job.source.file_name} "
               f"(killed, out of memory or crashed in native code): {exc}".rstrip(": ")),
        started_at=time.time(), versions=library_versions())


def _mill_and_text(mill: Mill | str | os.PathLike) -> tuple[Mill, str]:
    if not isinstance(mill, Mill):
        mill = load_mill(mill)
    if not mill.source:
        raise MillFileError("run_campaign needs the mill file itself (load it with "
                            "ident.load_mill) so that the store can keep it")
    try:
        text = Path(mill.source).read_text(encoding="utf-8")
    except OSError as exc:
        raise MillFileError(f"cannot read mill file: {exc}", path=mill.source) from None
    return mill, text


# ---- the campaign -------------------------------------------------------------------
def run_campaign(directory: str | os.PathLike, mill: Mill | str | os.PathLike, store: str, *,
                 workers: int | None = None, scheduler: str | None = None,
                 settings: Settings = Settings(), progress: bool = True,
                 retry_failed: bool = False, process: ProcessFn = process_recording,
                 tasks_per_worker: int = 25, memory_limit_mb: int | None = None,
                 min_age_s: float = 0.0,
                 on_stored: Callable[[str, RecordingOutcome], None] | None = None,
                 train: bool = False, train_samples: int = DEFAULT_LIBRARY_SAMPLES,
                 train_jobs: int = 2, refit: bool = True) -> CampaignSummary:
    """Process every recording under ``directory`` into the results store ``store``.

    Parameters
    ----------
    directory : path
        Campaign folder, searched recursively for ``*.mcap`` and ``*.csv``.
    mill : Mill or path
        The mill description (loaded from its file; the file is kept in the store).
    store : str
        SQLAlchemy URL, e.g. ``sqlite:///results.db``.
    workers : int, optional
        Local worker processes; default all cores; 0 runs in this process.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``); the recordings' paths must
        be readable by its workers.
    settings : Settings
        Processing settings; with the mill description they form the key that makes
        a rerun skip what is done.
    progress : bool
        Progress bar with ETA on stderr.
    retry_failed : bool
        Process again recordings stored as failed with the same key.
    process : callable
        ``process(path, mill, settings) -> RecordingOutcome``, importable by the
        workers; :func:`~ident.store.process.process_recording` by default.
    tasks_per_worker : int
        Local worker processes are replaced after this many recordings.
    memory_limit_mb : int, optional
        Address-space limit of each local worker process, MiB; a recording that
        needs more fails with ``MemoryError``.
    min_age_s : float
        Leave out recordings modified less than this many seconds ago (still arriving).
    on_stored : callable, optional
        Called as ``on_stored(file_name, outcome)`` after each commit.
    train : bool
        Diagnose with the mill's cached wear model, training it first when there is
        none (:func:`~ident.store.process.ensure_model`; ``ident campaign`` does so
        by default).  Only with ``settings.diagnose``, no ``settings.model`` and the
        real ``process``.
    train_samples, train_jobs : int
        Library size and simulation processes of that training.
    refit : bool
        The second pass (:mod:`ident.store.refit`): refit each recording that left a
        gap unidentified from the nearest recording that identified it; the refit is
        stored as a new row of that recording (its settings carry the start gaps),
        which the report reads instead of the first, and the first stays.  A refit
        that fails is not stored.

    Returns
    -------
    CampaignSummary

    Raises
    ------
    RecordingError
        ``directory`` does not exist.
    MillFileError, StoreError, CampaignError
        Bad mill file, store or scheduler.
    """
    t_begin = time.perf_counter()
    mill, mill_text = _mill_and_text(mill)
    sources = discover(directory, min_age_s=min_age_s)
    root = Path(directory).resolve()
    extra: dict[str, Any] = {}
    if process is process_recording:
        extra["stages"] = list(available_stages())
    if settings.model and not Path(settings.model).is_file():
        raise ModelArtifactError(f"wear model not found: {settings.model}")
    if (train and settings.diagnose and not settings.model and process is process_recording
            and "diagnose" in available_stages()):
        ensure_model(mill, samples=train_samples, jobs=train_jobs, progress=progress)
    model_file = model_path(mill, settings) if settings.diagnose else None
    if model_file is not None:
        from .discovery import content_hash

        extra["model_sha256"] = content_hash((model_file,))
    shash = settings_hash(settings, mill, extra=extra)
    st = open_store(store)
    try:
        st.register_mill(mill, mill_text)
        stored = st.stored_keys(shash)
        todo: deque[_Job] = deque()
        failed_before: list[tuple[str, str]] = []  # (file_name, hash), then (file_name, error)
        for s in sources:
            status = stored.get((s.file_name, s.content_sha256))
            if status is None:
                todo.append(_Job(s))
            elif status == "failed" and retry_failed:
                todo.append(_Job(s, replace=True))
            elif status == "failed":
                failed_before.append((s.file_name, s.content_sha256))
        n_skipped = len(sources) - len(todo)
        if failed_before:
            errors = st.failed_errors(shash)
            failed_before = [(f, errors.get((f, h), "")) for f, h in failed_before]
        by_key = {(s.file_name, s.content_sha256): s for s in sources}

        def pending_refits() -> list[_Job]:
            if not (refit and settings.fit):
                return []
            jobs = []
            for r in neighbour_starts(st.fit_summaries(shash)):
                src = by_key.get((r.file_name, r.content_sha256))
                if src is None:  # no longer under this folder
                    continue
                s2 = replace(settings, starts=r.starts)
                h2 = settings_hash(s2, mill, extra=extra)
                if (r.file_name, r.content_sha256) not in st.stored_keys(h2):
                    jobs.append(_Job(src, settings=s2, refit=(r, h2)))
            return jobs

        if not todo and not pending_refits():
            run_id = st.start_run(directory=str(root), mill=mill, settings_hash=shash,
                                  settings=settings.to_dict(), executor="none",
                                  host=socket.gethostname(), versions=library_versions(),
                                  n_found=len(sources), n_skipped=n_skipped)
            st.finish_run(run_id, status="finished", n_done=0, n_failed=0)
            return CampaignSummary(run_id=run_id, store=st.url, n_found=len(sources),
                                   n_skipped=n_skipped, n_done=0, n_failed=0,
                                   failed=tuple(failed_before),
                                   elapsed_s=time.perf_counter() - t_begin, executor="none")
        ex = _make_executor(process, workers, scheduler, tasks_per_worker=tasks_per_worker,
                            memory_limit_mb=memory_limit_mb)
        run_id = st.start_run(directory=str(root), mill=mill, settings_hash=shash,
                              settings=settings.to_dict(), executor=ex.name,
                              host=socket.gethostname(), versions=library_versions(),
                              n_found=len(sources), n_skipped=n_skipped)
        counts = {"done": 0, "failed": 0, "refit": 0}
        failed_now: list[tuple[str, str]] = []
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="rec", desc=f"campaign {mill.name}", file=sys.stderr,
                   disable=not progress, dynamic_ncols=True, smoothing=0.1)
        status = "interrupted"
        try:
            def store_one(job: _Job, outcome: RecordingOutcome) -> None:
                key = RecordingKey(job.source.file_name, job.source.content_sha256, shash)
                outcome = _write(st, run_id, key, outcome, mill=mill, job=job, root=root)
                counts[outcome.status] += 1
                if not outcome.ok:
                    failed_now.append((job.source.file_name, outcome.error or ""))
                bar.update(1)
                bar.set_postfix(failed=counts["failed"], refresh=False)
                if on_stored is not None:
                    on_stored(job.source.file_name, outcome)

            _drive(ex, todo, mill, settings, store_one)
            refits = deque(pending_refits())  # the second pass, on what is stored now
            rbar = tqdm(total=len(refits), unit="rec", desc="refit from neighbours",
                        file=sys.stderr, disable=not progress or not refits,
                        dynamic_ncols=True)

            def store_refit(job: _Job, outcome: RecordingOutcome) -> None:
                r, h2 = job.refit
                rbar.update(1)
                if not outcome.ok:  # the first fit stays: a failed refit is only said
                    if progress:
                        print(f"ident campaign: refit of {r.file_name} from {r.neighbour} "
                              f"failed: {outcome.error}", file=sys.stderr)
                    return
                note = {"stage": "fit", "kind": "refit_from_neighbour", "channel": None,
                        "t_start": None, "t_end": None, "fatal": False,
                        "message": f"refitted from the gaps of {r.neighbour} (the first fit "
                                   f"did not identify {', '.join(r.missing)})"}
                outcome = replace(outcome, quality=tuple(outcome.quality) + (note,))
                key = RecordingKey(job.source.file_name, job.source.content_sha256, h2)
                if _write(st, run_id, key, outcome, mill=mill, job=job, root=root).ok:
                    counts["refit"] += 1

            try:
                _drive(ex, refits, mill, settings, store_refit)
            finally:
                rbar.close()
            status = "finished"
        finally:
            bar.close()
            ex.close(cancel=status != "finished")
            st.finish_run(run_id, status=status, n_done=counts["done"],
                          n_failed=counts["failed"])
        return CampaignSummary(
            run_id=run_id, store=st.url, n_found=len(sources), n_skipped=n_skipped,
            n_done=counts["done"], n_failed=counts["failed"],
            failed=tuple(sorted(failed_before + failed_now)),
            elapsed_s=time.perf_counter() - t_begin, executor=ex.name, n_refit=counts["refit"])
    finally:
        st.close()


def _write(st: Store, run_id: int, key: RecordingKey, outcome: RecordingOutcome, *, mill: Mill,
           job: _Job, root: Path) -> RecordingOutcome:
    """Store one outcome; a result the database refuses is stored as failed instead."""
    import sqlalchemy as sa

    kw = dict(mill=mill, files=job.source.member_names(root), size_bytes=job.source.size_bytes,
              replace=job.replace)
    try:
        st.write_outcome(run_id, key, outcome, **kw)
        return outcome
    except (sa.exc.DataError, sa.exc.StatementError) as exc:
        if isinstance(exc, sa.exc.OperationalError):
            raise StoreError(f"cannot write to the results store {st.url}: {exc.orig}") from None
        bad = replace(outcome, status="failed", stage="store", error_kind=type(exc).__name__,
                      error=f"store: the database refused the results: {exc.orig or exc}",
                      segments=(), taf=(), fit=None, transient_fits=(), diagnosis=None)
        st.write_outcome(run_id, key, bad, **kw)
        return bad


def _drive(ex, todo: deque[_Job], mill: Mill, settings: Settings,
           store_one: Callable[[_Job, RecordingOutcome], None]) -> None:
    """Keep the executor busy, store outcomes as they come, isolate worker crashes."""
    inflight: dict[Any, _Job] = {}
    suspects: deque[_Job] = deque()
    idle_restarts = 0

    def submit(job: _Job) -> bool:
        try:
            inflight[ex.submit(str(job.source.path), mill, job.settings or settings)] = job
        except cf.process.BrokenProcessPool:  # a worker died since the last look
            return False
        return True

    while todo or suspects or inflight:
        broken = False
        if suspects:
            if not inflight:
                job = suspects.popleft()
                job.alone = True
                if not submit(job):
                    suspects.appendleft(job)
                    broken = True
        else:
            while todo and len(inflight) < ex.capacity:
                job = todo.popleft()
                if not submit(job):
                    todo.appendleft(job)
                    broken = True
                    break
        if not broken:
            for fut in ex.wait(inflight):
                job = inflight.pop(fut)
                try:
                    outcome = fut.result()
                except cf.process.BrokenProcessPool as exc:
                    broken = True
                    if job.alone:
                        store_one(job, _worker_died(job, exc))
                    else:
                        suspects.append(job)
                    continue
                except Exception as exc:  # noqa: BLE001 - e.g. dask KilledWorker
                    outcome = RecordingOutcome(status="failed", stage="worker",
                                               error=describe_error("worker", exc),
                                               error_kind=type(exc).__name__,
                                               started_at=time.time(),
                                               versions=library_versions())
                store_one(job, outcome)
                idle_restarts = 0
        if broken:
            # every other recording in flight is lost with the pool: keep finished ones,
            # retry the rest one at a time to find the one that kills its worker
            cf.wait(list(inflight))
            for fut, job in list(inflight.items()):
                if fut.exception() is None:
                    store_one(job, fut.result())
                else:
                    suspects.append(job)
            if not inflight:
                idle_restarts += 1
                if idle_restarts > 3:
                    raise CampaignError("the worker processes die as they start (see the "
                                        "messages above; memory limit too low?)")
            inflight.clear()
            ex.restart()
