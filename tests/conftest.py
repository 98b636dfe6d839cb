"""Shared fixtures of the test suite (others add theirs below)."""

from __future__ import annotations

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
