"""Shared fixtures of the test suite (others add theirs below)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from ident import Mill, load_mill

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository's top directory."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def mill_path(repo_root: Path) -> Path:
    """The shipped stand's mill file, ``data/mills/hsm-f1.toml``."""
    return repo_root / "data" / "mills" / "hsm-f1.toml"


@pytest.fixture(scope="session")
def mill(mill_path: Path) -> Mill:
    """The shipped stand (seed Fig. 2), loaded once; it is immutable."""
    return load_mill(mill_path)


@pytest.fixture(scope="session", autouse=True)
def _hermetic_cache(tmp_path_factory):
    """``$IDENT_CACHE`` in a fresh folder: no wear model a developer trained leaks into a test.

    Compiled integrators (``jit/``, keyed by the hash of their source) are still shared
    with the developer's cache, so that a local run does not compile them again.
    """
    old = os.environ.get("IDENT_CACHE")
    user = Path(old) if old else Path.home() / ".cache" / "ident"
    cache = tmp_path_factory.mktemp("ident-cache")
    try:
        (user / "jit").mkdir(parents=True, exist_ok=True)
        (cache / "jit").symlink_to(user / "jit", target_is_directory=True)
    except OSError:  # a read-only home: compile into the fresh folder
        pass
    os.environ["IDENT_CACHE"] = str(cache)
    yield cache
    if old is None:
        os.environ.pop("IDENT_CACHE", None)
    else:
        os.environ["IDENT_CACHE"] = old


#: Test modules that take minutes, longest first (seconds on one worker, from the slowest
#: tests of a run of the suite on this 2-core box, 2026-12-05: notebooks ~460, fit_plant
#: ~460, fit ~250, discrepancy_hidden ~180, campaign_e2e ~180, diagnose ~150, fit_cli ~140
#: (once its --start-from test stopped after one run), pipelines ~60, diagnose_cold ~50;
#: 23.4 min in all, before that change).  ``make test`` runs each module on one xdist
#: worker (``--dist loadscope``), and workers take modules in collection order: collecting
#: these first lets the short modules fill in around them instead of one long module
#: starting last (a run of 2026-12-03 ended with one worker idle for 6.5 min while
#: notebooks and pipelines ran).
SLOW_MODULES = ("test_notebooks.py", "test_fit_plant.py", "test_fit.py",
                "test_discrepancy_hidden.py", "test_campaign_e2e.py", "test_diagnose.py",
                "test_fit_cli.py", "test_pipelines.py", "test_diagnose_cold.py",
                "test_simulate_independent.py", "test_fit_recovery.py")


def pytest_collection_modifyitems(config, items):
    """Longest modules first (a stable sort: the order inside each module is kept)."""
    rank = {name: i for i, name in enumerate(SLOW_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
