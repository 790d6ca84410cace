"""The point cloud the report shows: ``fused.ply`` from the depth stage when the folder has
one (read by :func:`rgbd_calib.core.ply.read_ply`), else a preview
back-projected from the dataset's depth frames.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ...core.ply import read_ply

MAX_VIEW_POINTS = 40000  # points in the 3D view and the static cloud figures
PREVIEW_FRAMES = 5  # depth frames per camera in the preview cloud's temporal median


class Cloud:
    """Points (N,3) in the reference frame (m), camera index (N,) into ``names``, colours
    (N,3) uint8 or None, and where they came from (one sentence for the report)."""

    def __init__(
        self,
        points: np.ndarray,
        camera: np.ndarray,
        names: list[str],
        rgb: np.ndarray | None,
        source: str,
    ):
        self.points, self.camera, self.names, self.rgb, self.source = (
            points,
            camera,
            names,
            rgb,
            source,
        )


def _subsample(n: int, keep: int) -> np.ndarray:
    """Deterministic even subsample of ``range(n)`` to at most ``keep`` indices."""
    if n <= keep:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, keep).astype(int))


def load_cloud(report: dict[str, Any], folder: Path) -> tuple[Cloud | None, str]:
    """The cloud the report shows: ``folder/fused.ply`` when present (the depth stage's fused
    cloud), else a preview from the dataset's depth frames; ``(None, why)`` without depth."""
    cams = [c for c, v in report["cameras"].items() if v["calibrated"]]
    ply = Path(folder) / "fused.ply"
    if ply.is_file():
        points, rgb, cam, names = read_ply(ply)
        names = names or cams
        if cam is None:
            cam = np.zeros(len(points), dtype=int)
        order = {c: i for i, c in enumerate(report["cameras"])}
        remap = np.array([order.get(nm, -1) for nm in names] or [-1])
        cam = remap[np.clip(cam, 0, len(remap) - 1)]
        idx = _subsample(len(points), MAX_VIEW_POINTS)
        ok = cam[idx] >= 0
        idx = idx[ok]
        return Cloud(
            points[idx],
            cam[idx],
            list(report["cameras"]),
            None if rgb is None else rgb[idx],
            f"fused.ply: {len(points):,} points from the depth stage (showing {len(idx):,})",
        ), ""
    path = report["dataset"].get("path")
    depth_cams = [c for c in cams if c in report["dataset"].get("depth_cameras", [])]
    if not path or not Path(path).is_dir():
        return None, (
            f"no fused.ply in {folder} and the dataset folder {path} is not "
            "available: no point cloud to show"
        )
    if not depth_cams:
        return None, "no camera of the dataset has depth frames: no point cloud to show"
    return _preview_cloud(report, Path(path), depth_cams), ""


def _preview_cloud(report: dict[str, Any], dataset: Path, cams: list[str]) -> Cloud | None:
    """Each camera's static scene: the temporal median of a few depth frames (the moving
    board mostly drops out), back-projected on a pixel grid (pinhole, the rig.yaml depth
    scale; no depth-scale correction) and moved into the reference frame."""
    from ...model.dataset import read_color_image, read_depth_image

    order = list(report["cameras"])
    per_cam = MAX_VIEW_POINTS // max(len(cams), 1)
    pts, idx, cols = [], [], []
    for name in cams:
        cam = report["cameras"][name]
        intr = cam["intrinsics"]
        w, h = intr["width"], intr["height"]
        frames = sorted(p.stem for p in (dataset / name / "depth").glob("*.png"))
        if not frames:
            continue
        frames = [frames[i] for i in _subsample(len(frames), PREVIEW_FRAMES)]
        step = max(1, int(math.ceil(math.sqrt(w * h / (per_cam * 1.5)))))
        vs, us = np.mgrid[step // 2 : h : step, step // 2 : w : step]
        stack, rgb = [], []
        for f in frames:
            d = read_depth_image(dataset / name / "depth" / f"{f}.png", w, h)[vs, us]
            stack.append(np.where(d > 0, d * intr["depth_scale"], np.nan))
            color = next((p for p in (dataset / name / "color").glob(f"{f}.*")), None)
            if color is not None:
                rgb.append(read_color_image(color, w, h)[vs, us, ::-1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            z = np.nanmedian(np.stack(stack), axis=0)
        ok = np.isfinite(z)
        x = (us[ok] - intr["cx"]) / intr["fx"] * z[ok]
        y = (vs[ok] - intr["cy"]) / intr["fy"] * z[ok]
        p_cam = np.column_stack([x, y, z[ok]])
        T = np.asarray(cam["T_ref_cam"], dtype=float)
        keep = _subsample(len(p_cam), per_cam)
        pts.append((p_cam @ T[:3, :3].T + T[:3, 3])[keep])
        idx.append(np.full(len(keep), order.index(name)))
        cols.append(
            np.median(np.stack(rgb), axis=0)[ok][keep].astype(np.uint8)
            if rgb
            else np.full((len(keep), 3), 160, np.uint8)
        )
    if not pts:
        return None
    return Cloud(
        np.concatenate(pts),
        np.concatenate(idx),
        order,
        np.concatenate(cols),
        f"preview (no fused.ply yet): median of {PREVIEW_FRAMES} depth frames per "
        f"camera from {dataset}, {sum(len(p) for p in pts):,} points, rig.yaml depth "
        "scale, no depth-scale correction",
    )
