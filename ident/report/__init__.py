"""The wear trend report of a results store: one self-contained HTML file.

    load_results(store) ──► analyse_mill (trend.fit_trend, trend.crossing, statuses)
                                 │
                                 ▼
                        figures (matplotlib Agg → PNG data URIs) ──► html.render
                                 └──► status.status_json (report --json, SI, ISO dates)

Per mill: a traffic-light summary per element and bearing, gap trends with worn
and critical limits and a forecast (with its 95 % interval) of when each limit
is reached, TAF against static torque from the measurements (seed Fig. 4),
natural-frequency amplitude and phase trends, bearing clearance trends, a
data-quality summary and the recordings that failed.
"""

from .build import Assessment, MillSection, ReportSummary, analyse_mill, build_report
from .status import RemainingLife, remaining_life, status_json
from .trend import Crossing, Trend, crossing, fit_trend

__all__ = ["build_report", "analyse_mill", "ReportSummary", "MillSection", "Assessment",
           "fit_trend", "crossing", "Trend", "Crossing", "status_json", "remaining_life",
           "RemainingLife"]
