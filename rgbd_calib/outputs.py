"""Writes a calibration's results into its output folder, atomically.

Everything is first written into a staging folder beside the outputs, then each file is renamed
into place, ``extrinsics.yaml`` last: an interrupted or failed run leaves any earlier result
untouched, and never a half-written file.

``report.json`` (schema: docs/report_schema.md) holds every number the human report shows, so
``rgbd-calib report DIR`` (:func:`rgbd_calib.report.rebuild_report`) rebuilds ``report.html``
from the saved folder alone.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from .calibrate import CalibrationResult
from .depth import write_fused_ply
from .exports import write_exports
from .report import dump_report, report_dict, write_report_html
from .results import write_extrinsics
from .rig import Rig
from .yamlio import to_builtin

Progress = Callable[[str, int, int], Callable[[int], None]]


def write_outputs(
    result: CalibrationResult,
    rig: Rig,
    out_dir: Path,
    fused_ply: Path | None = None,
    pairs: list[dict[str, Any]] | None = None,
    depth_scale: dict[str, dict[str, float]] | None = None,
    progress: Progress | None = None,
) -> list[Path]:
    """Write extrinsics.yaml, report.json, report.html, config_resolved.yaml and exports/
    into out_dir (and fused.ply, copied from ``fused_ply`` when the depth stage made one).

    Without ``fused_ply`` an older ``out_dir/fused.ply`` is removed (it would belong to another
    run) and the report previews the cloud from the dataset's depth frames."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = out_dir / f".staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        if result.depth is not None:
            pairs = pairs if pairs is not None else result.depth.pairs
            depth_scale = depth_scale if depth_scale is not None else (
                result.depth.depth_scale_dict())
            if fused_ply is None and result.depth.clouds:
                T_ref_cam = {c: e.T_ref_cam for c, e in result.extrinsics.cameras.items()}
                pts, cols, idx, names = result.depth.fused(
                    T_ref_cam, result.config.depth.fused_voxel_m)
                write_fused_ply(stage / "fused.ply", pts, cols, idx, names)
        report = report_dict(result, rig, pairs, depth_scale)
        (stage / "report.json").write_text(dump_report(report))
        if fused_ply is not None:
            shutil.copyfile(fused_ply, stage / "fused.ply")
        write_report_html(report, stage, progress=progress)
        (stage / "config_resolved.yaml").write_text(
            yaml.safe_dump(to_builtin(result.config.model_dump()), sort_keys=False)
        )
        boards = result.bundle.T_ref_board if result.bundle else result.posegraph.T_ref_board
        write_exports(result.extrinsics, stage, rig=rig, board_poses=boards)
        write_extrinsics(result.extrinsics, stage / "extrinsics.yaml")
        if not (stage / "fused.ply").exists():
            (out_dir / "fused.ply").unlink(missing_ok=True)
        written = []
        for path in sorted(stage.rglob("*"), key=lambda p: p.name == "extrinsics.yaml"):
            if path.is_dir():
                continue
            target = out_dir / path.relative_to(stage)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)
            written.append(target)
        return written
    finally:
        shutil.rmtree(stage, ignore_errors=True)
