"""The calibration report: ``report.json`` (versioned schema, docs/report_schema.md) and one
self-contained, offline ``report.html``.

It answers three questions: can I trust these extrinsics, which camera is weak, what do I do
next. Data flows one way::

    CalibrationResult --build.report_dict--> report.json (primary numbers)
        --build.finalize_report--> + summary, co-visibility, coverage, findings (derived, pure)
        --html.write_report_html--> report.html (+ fused.ply, or a preview cloud from the dataset)

Everything the HTML shows comes from ``report.json``, ``fused.ply`` and the dataset folder
recorded in it, so :func:`rebuild_report` reproduces both files byte for byte (there is no
timestamp).

Modules: ``schema`` (the key tree, its checker, thresholds, JSON), ``numbers`` (statistics),
``build`` (the report dict), ``findings`` (one rule per warning code; the rules by subject
in ``findings_*``), ``cloud`` (fused.ply or
a preview cloud), ``layout`` (display frame, frusta), ``figures`` (matplotlib), ``viewer``
(the inline 3D view), ``html`` (the page, one function per section), ``rebuild``
(``rgbd-calib report DIR``).
"""

from .build import depth_only_report_dict, error_map, finalize_report, pair_entry, report_dict
from .cloud import Cloud, load_cloud
from .findings import RULES, findings, report_verdict
from .html import render_html, write_report_html
from .numbers import histogram_edges_px, stats
from .rebuild import rebuild_report
from .schema import (
    REPORT_SCHEMA,
    REPORT_SCHEMA_VERSION,
    ReportError,
    dump_report,
    finite_or_null,
    schema_blocks,
    schema_paths,
    validate_report,
)
from .storage import VIEWS_FILE, VIEWS_INLINE_MAX, load_report, write_report_json

__all__ = [
    "REPORT_SCHEMA",
    "REPORT_SCHEMA_VERSION",
    "RULES",
    "VIEWS_FILE",
    "VIEWS_INLINE_MAX",
    "Cloud",
    "ReportError",
    "depth_only_report_dict",
    "dump_report",
    "error_map",
    "finalize_report",
    "findings",
    "finite_or_null",
    "histogram_edges_px",
    "load_cloud",
    "load_report",
    "pair_entry",
    "rebuild_report",
    "render_html",
    "report_dict",
    "report_verdict",
    "schema_blocks",
    "schema_paths",
    "stats",
    "validate_report",
    "write_report_html",
    "write_report_json",
]
