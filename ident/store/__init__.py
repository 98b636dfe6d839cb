"""Campaigns at scale: a results store (SQLAlchemy) and the runner that fills it.

    campaign folder ──► discover (file name + content SHA-256)
                            │  skip what the store holds with the same settings
                            ▼
          worker processes / Dask: process_recording(path, mill, settings)
             read → segment → TAF → fit → diagnose  ──►  RecordingOutcome (cli.md dicts)
                            │
                            ▼
          parent process: Store.write_outcome — one transaction per recording
                            │
                            ▼
          load_results(url) -> DataFrames  ──►  ident.report, notebooks

SQLite is the embedded default (``sqlite:///results.db``), PostgreSQL by URL
(``postgresql+psycopg://user@host/db``).  Tables: :mod:`ident.store.schema`.
"""

from .campaign import CampaignError, CampaignSummary, default_workers, run_campaign
from .discovery import RecordingSource, discover
from .load import RESULT_TABLES, load_results
from .outcome import RecordingOutcome
from .process import (Settings, available_stages, ensure_model, library_versions,
                      process_recording, settings_hash)
from .sample import SampleCampaign, make_sample_campaign
from .store import RecordingKey, Store, open_store

__all__ = ["open_store", "Store", "RecordingKey", "load_results", "RESULT_TABLES",
           "run_campaign", "CampaignSummary", "CampaignError", "default_workers",
           "Settings", "process_recording", "settings_hash", "library_versions",
           "available_stages", "make_sample_campaign", "SampleCampaign", "RecordingOutcome",
           "RecordingSource", "discover", "ensure_model"]
