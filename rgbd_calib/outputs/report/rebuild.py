"""``rgbd-calib report DIR``: rebuild ``report.json`` and ``report.html`` of a calibration
folder from its saved results alone.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ...core.progress import Progress
from .build import agrees_from_reason, finalize_report, kinds_from_reason
from .html import write_report_html
from .schema import REPORT_SCHEMA_VERSION, ReportError, validate_report
from .storage import VIEWS_INLINE_MAX, load_report, write_report_json


def rebuild_report(out_dir: Path, progress: Progress | None = None) -> Path:
    """Rebuild ``report.json`` and ``report.html`` of a calibration folder from its saved
    results alone (``report.json``, ``extrinsics.yaml``, ``fused.ply`` and the dataset folder
    recorded in the report; its per-view side file when it has one). The derived sections are
    recomputed, so a report of this schema comes back byte-identical, its side file too.
    Returns the path of ``report.html``."""
    out_dir = Path(out_dir)
    path = out_dir / "report.json"
    report, had_side_file = _read_report(path, out_dir)
    report = _refinalize(report, path)
    _check_extrinsics(report, out_dir / "extrinsics.yaml", path)
    write_report_json(report, out_dir, 0 if had_side_file else VIEWS_INLINE_MAX)
    return write_report_html(report, out_dir, progress)


def _read_report(path: Path, out_dir: Path) -> tuple[dict[str, Any], bool]:
    """The saved ``report.json`` with its views inline, checked to be a report of this
    schema's major version, and whether its views were in a side file."""
    if not path.is_file():
        raise ReportError(
            f"{path}: missing; is {out_dir} the --out folder of rgbd-calib calibrate?"
        )
    try:
        had_side_file = "views_file" in json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, TypeError):
        had_side_file = False  # load_report says what is wrong
    report = load_report(path)
    if not isinstance(report, dict) or "cameras" not in report:
        raise ReportError(f"{path}: not an rgbd-calib report; re-run calibrate")
    version = str(report.get("schema_version", "?"))
    if version.split(".")[0] != REPORT_SCHEMA_VERSION.split(".")[0]:
        raise ReportError(
            f"{path}: report schema {version} cannot be read by this rgbd-calib "
            f"(schema {REPORT_SCHEMA_VERSION}); re-run calibrate"
        )
    return report, had_side_file


def _refinalize(report: dict[str, Any], path: Path) -> dict[str, Any]:
    """The saved report brought to this schema version, its derived sections recomputed and
    the result validated."""
    try:
        report["schema_version"] = REPORT_SCHEMA_VERSION
        for pair in report.get("pairs") or []:  # 1.1 added it; an older report has no value
            if isinstance(pair, dict):
                pair.setdefault("rmse_final_mm", None)
                pair.setdefault("agrees", agrees_from_reason(pair))  # 1.9
                pair.setdefault("rejected_by", kinds_from_reason(pair))  # 1.18
        if isinstance(report.get("pose_graph"), dict):  # 1.2 added it
            report["pose_graph"].setdefault("model_error", [])
        report = finalize_report(report)
    except (KeyError, TypeError, ValueError) as exc:
        raise ReportError(
            f"{path}: incomplete report ({exc!r}; written by an older "
            "rgbd-calib?); re-run calibrate"
        ) from None
    errors = validate_report(report)
    if errors:
        raise ReportError(
            f"{path}: does not match report schema {REPORT_SCHEMA_VERSION}: "
            f"{'; '.join(errors[:3])}; re-run calibrate"
        )
    return report


def _check_extrinsics(report: dict[str, Any], ext_path: Path, path: Path) -> None:
    """``extrinsics.yaml`` (when present) must hold the report's camera poses: both files
    come from the same run."""
    from ...model.results import load_extrinsics

    if not ext_path.is_file():
        return
    ext = load_extrinsics(ext_path)
    for name, cam in ext.cameras.items():
        saved = report["cameras"].get(name, {}).get("T_ref_cam")
        if saved is None or not np.allclose(saved, cam.T_ref_cam, atol=1e-6):
            raise ReportError(
                f"{ext_path}: camera {name} differs from {path}; the two "
                "files come from different runs; re-run calibrate"
            )
