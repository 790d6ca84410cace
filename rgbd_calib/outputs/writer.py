"""Writes a calibration's results into its output folder, atomically.

Everything is first written into a staging folder beside the outputs, then each file is renamed
into place, ``extrinsics.yaml`` last: an interrupted or failed run leaves any earlier result
untouched, and never a half-written file.

``report.json`` (schema: docs/report_schema.md) holds every number the human report shows, so
``rgbd-calib report DIR`` (:func:`.report.rebuild_report`) rebuilds ``report.html``
from the saved folder alone.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..core.config import write_config
from ..core.depth_model import DepthModel
from ..core.interrupts import mark_committed, sigint_deferred
from ..core.ply import write_fused_ply
from ..core.progress import Progress
from ..core.yamlio import to_builtin, write_yaml
from ..depth.clouds import fuse_clouds
from ..depth.registration import DepthPair, pair_dicts
from ..depth.stage import DepthRefinement
from ..model.board import refined_board, refined_multiface
from ..model.board_file import save_board
from ..model.calib_folder import BOARD_REFINED_FILE
from ..model.dataset import FolderDataset
from ..model.depth_model_file import DEPTH_MODEL_FILE, save_depth_models
from ..model.results import Extrinsics, PoseEdge, write_extrinsics
from ..model.rig import Rig, save_rig
from ..pipelines.calibrate import CalibrationResult
from ..pipelines.check import CheckRun
from ..pipelines.posegraph import POSEGRAPH_CONFIG, POSEGRAPH_REPORT, PosegraphRun
from ..pipelines.refine import IN_MEMORY, RefineResult, refine_summary
from ..solve.ladder import refined_rig
from .exports import write_exports
from .report import (
    depth_only_report_dict,
    dump_report,
    finite_or_null,
    report_dict,
    report_verdict,
    write_report_html,
)
from .report.storage import VIEWS_FILE, VIEWS_INLINE_MAX, write_report_json


@contextmanager
def staged(out_dir: Path, replaces: tuple[str, ...] = ()) -> Iterator[Path]:
    """A staging folder for one run's outputs; when the block ends without error every file
    in it is renamed into ``out_dir`` (sub-folders kept), ``extrinsics.yaml`` last, and each
    name (file or folder) in ``replaces`` that the run did not write is removed from
    ``out_dir`` (it would belong to an older run), and each folder of ``replaces`` it did
    write replaces the old one whole (another rig's ``exports/open3d/cam_*.json`` would
    stay beside this run's otherwise). On an error ``out_dir`` is left exactly
    as it was. A Ctrl-C during the renames waits for them (:func:`sigint_deferred`), so
    ``out_dir`` holds either the earlier results or this run's, never a mix."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = out_dir / f".staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        yield stage
        # Ctrl-C waits for the renames: cut in the middle, out_dir would hold two runs
        with sigint_deferred():
            for name in replaces:
                if (stage / name).is_dir() and (out_dir / name).is_dir():
                    shutil.rmtree(out_dir / name)  # a folder is replaced whole: no stale file
                elif not (stage / name).exists():
                    if (out_dir / name).is_dir():
                        shutil.rmtree(out_dir / name)
                    else:
                        (out_dir / name).unlink(missing_ok=True)
            for path in sorted(stage.rglob("*"), key=lambda p: p.name == "extrinsics.yaml"):
                if not path.is_dir():
                    target = out_dir / path.relative_to(stage)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(path, target)
            mark_committed(out_dir)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _written(stage: Path, out_dir: Path) -> list[Path]:
    """The files of ``stage`` as they will stand in ``out_dir``, ``extrinsics.yaml`` last."""
    files = sorted(stage.rglob("*"), key=lambda p: p.name == "extrinsics.yaml")
    return [out_dir / p.relative_to(stage) for p in files if not p.is_dir()]


def used_edges(result: CalibrationResult) -> list[PoseEdge]:
    """The per-view ``T_cam_board`` edges the pose graph used (the exports' Edges.csv and g2o
    edges), with their PnP covariances: taken from the edge list the pose graph was solved on
    (``PoseGraphResult.edges``), not rebuilt from ``result.observations``, which are the views
    detected again with a refined lens when the bundle adjustment refined it."""
    return list(result.posegraph.used_pose_edges)


RIG_REFINED = "rig_refined.yaml"
BOARD_REFINED = BOARD_REFINED_FILE


def write_outputs(
    result: CalibrationResult,
    rig: Rig,
    out_dir: Path,
    fused_ply: Path | None = None,
    pairs: list[dict[str, Any]] | None = None,
    depth_scale: dict[str, dict[str, float]] | None = None,
    progress: Progress | None = None,
    warn: Callable[[str], None] | None = None,
    views_inline_max: int = VIEWS_INLINE_MAX,
) -> list[Path]:
    """Write extrinsics.yaml, report.json, report.html, config_resolved.yaml and exports/
    into out_dir (and fused.ply, copied from ``fused_ply`` when the depth stage made one;
    rig_refined.yaml, rig.yaml's format, when the bundle adjustment refined the intrinsics or
    some were calibrated from scratch;
    depth_model.yaml, each camera's depth model, when the depth stage fitted them;
    board_refined.yaml, the board file with the back sheet (a multi-face target: its faces)
    where the bundle adjustment found it, when it refined the board).

    Without ``fused_ply`` an older ``out_dir/fused.ply`` is removed (it would belong to another
    run) and the report previews the cloud from the dataset's depth frames. Above
    ``views_inline_max`` views the per-view detail of report.json is written to
    report_views.ndjson.gz (:mod:`rgbd_calib.outputs.report.storage`).

    A finished calibration is never lost to its side products: when ``report.html`` or an
    export cannot be made, that file (or ``exports/``) is left out and ``warn(why)`` says so
    (default: a Python warning); extrinsics.yaml and report.json are written all the same."""
    out_dir = Path(out_dir)
    warn = warn or _python_warning
    rig = result.rig or rig  # with the first intrinsics of cameras calibrated from scratch
    with staged(out_dir, replaces=("fused.ply", RIG_REFINED, BOARD_REFINED, VIEWS_FILE,
                                   DEPTH_MODEL_FILE, "report.html", "exports")) as stage:
        # the exports carry the intrinsics the extrinsics were solved with: the refined ones
        export_rig = rig
        if result.bundle is not None and result.bundle.intrinsics:
            export_rig = refined_rig(rig, result.bundle)
            save_rig(export_rig, stage / RIG_REFINED)
        elif getattr(result, "initial_intrinsics", None):
            save_rig(rig, stage / RIG_REFINED)  # intrinsics from scratch, held as first found
        model = result.bundle.board if result.bundle is not None else None
        if model is not None and not model.held and result.board is not None:
            save_board(refined_board(result.board, model.T_front_back), stage / BOARD_REFINED)
        faces = result.bundle.faces if result.bundle is not None else ()
        if result.board is not None and any(not f.held for f in faces):
            save_board(refined_multiface(result.board, {f.label: f.T_board_face for f in faces
                                                         if not f.held}), stage / BOARD_REFINED)
        if result.depth is not None:
            pairs = pairs if pairs is not None else pair_dicts(result.depth.pairs)
            depth_scale = depth_scale if depth_scale is not None else (
                result.depth.depth_scale_dict())
            fits = result.depth.depth_models
            if fits:
                save_depth_models({c: f.model for c, f in fits.items()},
                                  stage / DEPTH_MODEL_FILE,
                                  {c: {"evidence": {k: v for k, v in f.to_dict().items()
                                                    if k not in ("camera", "model")}}
                                   for c, f in fits.items()})
            if fused_ply is None and result.depth.clouds:
                T_ref_cam = {c: e.T_ref_cam for c, e in result.extrinsics.cameras.items()}
                pts, cols, idx, names = result.depth.fused(
                    T_ref_cam, result.config.depth.fused_voxel_m)
                write_fused_ply(stage / "fused.ply", pts, cols, idx, names)
        report = report_dict(result, rig, pairs, depth_scale)
        # the verdict goes into extrinsics.yaml and every export: a file read on its own says
        # what it is worth
        extrinsics = replace(result.extrinsics, verdict=report_verdict(report))
        # above views_inline_max views, the per-view detail goes to report_views.ndjson.gz
        write_report_json(report, stage, views_inline_max)
        if fused_ply is not None:
            shutil.copyfile(fused_ply, stage / "fused.ply")
        _html_or_warning(report, stage, out_dir, warn, progress)
        write_config(result.config, stage / "config_resolved.yaml")
        boards = result.bundle.T_ref_board if result.bundle else result.posegraph.T_ref_board
        try:
            write_exports(extrinsics, stage, rig=export_rig, edges=used_edges(result),
                          board_poses=boards)
        except Exception as exc:  # noqa: BLE001 - an export is not worth the result
            shutil.rmtree(stage / "exports", ignore_errors=True)
            warn(f"exports/ not written ({_one_line(exc)}); extrinsics.yaml is complete "
                 "(rgbd_calib.write_exports makes them from it)")
        write_extrinsics(extrinsics, stage / "extrinsics.yaml")
        written = _written(stage, out_dir)
    return written


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0][:300]


def _html_or_warning(report: dict[str, Any], stage: Path, out_dir: Path,
                     warn: Callable[[str], None] | None, progress: Progress | None = None,
                     ) -> None:
    """``report.html`` into ``stage``; a page that cannot be drawn is left out with
    ``warn(why)`` (the result is worth more than its page)."""
    try:
        write_report_html(report, stage, progress=progress)
    except Exception as exc:  # noqa: BLE001 - the page is not worth the result
        (stage / "report.html").unlink(missing_ok=True)
        if warn is not None:
            warn(f"report.html not written ({_one_line(exc)}); report.json is complete: "
                 f"rgbd-calib report {out_dir} retries")


def _python_warning(message: str) -> None:
    warnings.warn(message, RuntimeWarning, stacklevel=3)


REFINE_REPORT = "refine_report.json"


@dataclass(frozen=True)
class DepthOnlyRun:
    """What a depth-only run (``rgbd-calib refine``) needs besides its extrinsics to write
    the calibration report: the dataset it read, where it started and how, and its depth
    measurements."""

    dataset: FolderDataset
    init: Path | None  # None: extrinsics given in memory
    method: str
    verdict: dict[str, Any]  # refine_verdict / fix_verdict
    pairs: list[DepthPair]
    scale_source: dict[str, str]  # camera -> board / given / unknown
    # camera -> the depth model (depth_model.yaml) or factor (report.json) next to --init
    given_scales: dict[str, float | DepthModel]
    depth_status: dict[str, Any]  # report.json ``depth``
    board_scales: dict[str, dict[str, float]] = field(default_factory=dict)  # factor, sigma
    timings_s: dict[str, float] = field(default_factory=dict)
    moved: list[str] | None = None  # --fix-others: the cameras the check found moved
    board_models: dict[str, DepthModel] = field(default_factory=dict)  # fitted on the board

    def depth_models(self) -> dict[str, DepthModel]:
        """The depth models the run's clouds were corrected with (depth_model.yaml of its
        output folder, so that a later check or refine applies them too)."""
        return {**{c: m for c, m in self.given_scales.items() if isinstance(m, DepthModel)
                   and self.scale_source.get(c) == "given"}, **self.board_models}

    def report(self, extrinsics: Extrinsics) -> dict[str, Any]:
        """report.json (schema 1.3, method ``depth``) of this run at ``extrinsics``."""
        scales: dict[str, dict[str, float | None]] = {
            c: {"factor": f.value("scale") if isinstance(f, DepthModel) else f, "sigma": None}
            for c, f in self.given_scales.items() if self.scale_source.get(c) == "given"}
        scales.update(self.board_scales)
        return depth_only_report_dict(
            extrinsics, self.dataset.rig, self.dataset.summary().to_dict(),
            refine_summary(self.init, self.method, self.verdict, self.scale_source,
                           self.moved),
            pair_dicts(self.pairs), self.depth_status, scales, self.timings_s)


def write_refine_outputs(
    extrinsics: Extrinsics,
    depth: DepthRefinement,
    out_dir: Path,
    method: str,
    init: Path | None,
    fused_voxel_m: float = 0.005,
    verdict: dict[str, Any] | None = None,
    run: DepthOnlyRun | None = None,
    warn: Callable[[str], None] | None = None,
) -> list[Path]:
    """Write a depth-only refinement into ``out_dir``: ``fused.ply`` (at the refined
    extrinsics), ``refine_report.json`` (method, starting file, every pair), with ``run``
    ``report.json`` and ``report.html`` (the calibration report, method ``depth``), and
    ``extrinsics.yaml`` (last). A report.html that cannot be drawn is left out with
    ``warn(why)``: the extrinsics are written all the same."""
    report = {**(verdict or {}), "method": method,
              "init": str(init) if init is not None else IN_MEMORY,
              "depth": depth.status_dict(), "pairs": pair_dicts(depth.pairs)}
    return _write_refined(extrinsics, depth.clouds, out_dir, fused_voxel_m,
                          json.dumps(to_builtin(report), indent=1, default=str), run, warn)


def write_refine(result: RefineResult, out_dir: str | os.PathLike,
                 warn: Callable[[str], None] | None = None) -> list[Path]:
    """Write a :func:`rgbd_calib.refine` result as ``rgbd-calib refine`` does: ``fused.ply``,
    ``refine_report.json``, ``report.json`` / ``report.html`` and ``extrinsics.yaml`` (with
    the verdict), staged (nothing half-written)."""
    depth = result.depth
    init = result.init_path
    run = DepthOnlyRun(result.dataset, init, result.method, result.outcome, depth.pairs,
                       depth.scale_source, result.depth_scales, depth.status_dict(),
                       depth.depth_scale_dict(), depth.timings_s,
                       board_models={c: f.model for c, f in depth.depth_models.items()})
    return write_refine_outputs(result.extrinsics, depth, Path(out_dir), result.method, init,
                                verdict=result.outcome, run=run, warn=warn or _python_warning)


CHECK_REPORT = "check.json"


def write_check_outputs(run: CheckRun, out_dir: Path, calib: Path) -> list[Path]:
    """``check.json``: per camera its status and move, every pair, the tolerance
    (docs/formats.md, "Check output")."""
    out_dir = Path(out_dir)
    with staged(out_dir) as stage:
        report = {"calib": str(calib), "depth_scale_source": run.scale_source,
                  **run.result.to_dict()}
        (stage / CHECK_REPORT).write_text(
            json.dumps(finite_or_null(to_builtin(report)), indent=1, allow_nan=False) + "\n")
        written = _written(stage, out_dir)
    return written


def write_fix_outputs(extrinsics: Extrinsics, run: CheckRun, pairs: list[DepthPair],
                      out_dir: Path, method: str, init: Path,
                      verdict: dict[str, Any], fused_voxel_m: float = 0.005,
                      depth_only: DepthOnlyRun | None = None,
                      warn: Callable[[str], None] | None = None) -> list[Path]:
    """``refine --fix-others``: ``fused.ply`` (at the fixed extrinsics),
    ``refine_report.json`` (verdict, the check, the re-registered pairs), with
    ``depth_only`` ``report.json`` and ``report.html``, and ``extrinsics.yaml`` (last)."""
    report = {**verdict, "method": method, "init": str(init), "fix_others": True,
              "check": {"depth_scale_source": run.scale_source, **run.result.to_dict()},
              "pairs": pair_dicts(pairs)}
    return _write_refined(extrinsics, run.clouds, out_dir, fused_voxel_m, json.dumps(
        finite_or_null(to_builtin(report)), indent=1, allow_nan=False), depth_only, warn)


def _write_refined(extrinsics: Extrinsics, clouds: dict[str, Any], out_dir: Path,
                   fused_voxel_m: float, report_text: str, run: DepthOnlyRun | None = None,
                   warn: Callable[[str], None] | None = None) -> list[Path]:
    """The folder of a depth-only run, staged: ``fused.ply`` of ``clouds`` at
    ``extrinsics``, ``refine_report.json`` (``report_text``), with ``run`` ``report.json``
    and ``report.html`` (a figure that fails costs the page, with ``warn``, not the run),
    then ``extrinsics.yaml``."""
    out_dir = Path(out_dir)
    with staged(out_dir, replaces=("fused.ply", "report.json", "report.html",
                                   DEPTH_MODEL_FILE)) as stage:
        T_ref_cam = {c: e.T_ref_cam for c, e in extrinsics.cameras.items()}
        pts, cols, idx = fuse_clouds(clouds, T_ref_cam, fused_voxel_m)  # index: names' order
        write_fused_ply(stage / "fused.ply", pts, cols, idx,
                        [c for c in clouds if c in T_ref_cam])
        (stage / REFINE_REPORT).write_text(report_text)
        if run is not None:
            report = run.report(extrinsics)
            (stage / "report.json").write_text(dump_report(report))
            _html_or_warning(report, stage, out_dir, warn)
            if models := run.depth_models():
                save_depth_models(models, stage / DEPTH_MODEL_FILE)
            extrinsics = replace(extrinsics, verdict=report_verdict(report))
        write_extrinsics(extrinsics, stage / "extrinsics.yaml")
        written = _written(stage, out_dir)
    return written


def write_posegraph_outputs(run: PosegraphRun, out_dir: Path) -> dict[str, Path]:
    """Write ``extrinsics.yaml``, ``posegraph_report.json``, ``posegraph_config.yaml`` (the
    resolved config) and ``exports/`` (edges the solution used, solved board poses) into
    ``out_dir``; returns the written paths by kind. ``extrinsics.yaml`` is moved into place
    last, so an interrupted run never leaves a fresh-looking result beside stale side files."""
    out_dir = Path(out_dir)
    with staged(out_dir) as stage:
        used = list(run.result.used_pose_edges)
        paths = write_exports(
            run.extrinsics,
            stage,
            edges=used,
            board_poses=run.result.T_ref_board,
            default_sigma_rotation_deg=run.result.sigma_rotation_deg_default,
            default_sigma_translation_mm=run.result.sigma_translation_mm_default,
        )
        paths["report"] = stage / POSEGRAPH_REPORT
        report = json.dumps(finite_or_null(run.to_dict()), indent=2, allow_nan=False)
        paths["report"].write_text(report + "\n")
        paths["config"] = stage / POSEGRAPH_CONFIG
        write_yaml(paths["config"], run.config.model_dump())
        paths["extrinsics"] = stage / "extrinsics.yaml"
        write_extrinsics(run.extrinsics, paths["extrinsics"])
    return {kind: out_dir / p.relative_to(stage) for kind, p in paths.items()}
