"""Load a results store into pandas, one DataFrame per table.

The report and the notebooks read the store through :func:`load_results` only.
"""

from __future__ import annotations

from typing import Any

import pandas as pd
import sqlalchemy as sa

from . import schema as S
from .store import Store, open_store

__all__ = ["load_results", "RESULT_TABLES"]

#: Keys of the dict :func:`load_results` returns.
RESULT_TABLES = ("recordings", "runs", "mills", "transients", "taf", "fits", "element_results",
                 "diagnoses", "features", "quality_issues")


def _read(conn: sa.Connection, query: Any) -> pd.DataFrame:
    res = conn.execute(query)
    return pd.DataFrame(res.all(), columns=list(res.keys()))


def load_results(store: str | Store, *, mill: str | None = None,
                 latest_only: bool = True) -> dict[str, pd.DataFrame]:
    """Read the store's tables into DataFrames.

    Parameters
    ----------
    store : str or Store
        SQLAlchemy URL of an existing store, or an open :class:`Store`.
    mill : str, optional
        Only recordings of this mill name.
    latest_only : bool
        Keep, per mill and file name, only the most recently stored row (a file
        re-processed with other settings, or whose content changed, appears once).

    Returns
    -------
    dict of str to DataFrame
        Keys :data:`RESULT_TABLES`.  ``recordings`` gains ``t0`` (UTC timestamp of
        the recording's start, from ``t0_ns``); every per-recording table gains
        ``file_name``, ``mill_name``, ``status`` and ``t0`` of its recording, so
        that trends need no join.  Units as in :mod:`ident.store.schema`.

    Raises
    ------
    StoreError
        The store does not exist or cannot be read.
    """
    own = isinstance(store, str)
    st = open_store(store, create=False) if own else store
    try:
        r = S.recordings.c
        if latest_only:
            keep = sa.select(sa.func.max(r.id)).group_by(r.mill_name, r.file_name)
        else:
            keep = sa.select(r.id)
        if mill is not None:
            keep = keep.where(r.mill_name == mill)
        with st.engine.connect() as conn:
            out: dict[str, pd.DataFrame] = {
                "recordings": _read(conn, sa.select(S.recordings).where(r.id.in_(keep))
                                    .order_by(r.id)),
                "runs": _read(conn, sa.select(S.runs).order_by(S.runs.c.id)),
                "mills": _read(conn, sa.select(S.mills)),
            }
            for t in S.CHILD_TABLES:
                out[t.name] = _read(conn, sa.select(t).where(t.c.recording_pk.in_(keep))
                                    .order_by(t.c.id))
    finally:
        if own:
            st.close()
    r = out["recordings"]
    r["t0"] = pd.to_datetime(r["t0_ns"].astype("Int64"), unit="ns", utc=True)
    link = r[["id", "file_name", "mill_name", "status", "t0"]].rename(
        columns={"id": "recording_pk"})
    for t in S.CHILD_TABLES:
        out[t.name] = out[t.name].merge(link, on="recording_pk", how="left")
    return out
