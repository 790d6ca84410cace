"""What a detector's edge offset does to the extrinsics, with and without its model.

    python tools/bench_edge_offset.py RENDER [--offsets 0 0.05 0.1] [--work DIR]
                                             [--edge-offset auto off]

On real prints the edge fit sees every marker larger by +0.05 to +0.16 px per edge, by camera
(its imaging: blur, sharpening, compression; docs/accuracy.md, "Corners on real photos"). The
renderer has no such offset, so it is put into the detections: the render is calibrated once
(``--refine none``) to fill a detection cache, then for each offset every marker edge in a copy
of that cache is moved outward by it (each corner by the offset along the outward normals of
its two edges) and the render calibrated again from the copy, once per ``bundle.edge_offset``
mode (``auto``: the offset modelled, the default; ``off``: read only). Printed per offset and
mode: the worst camera's error against ground_truth.yaml, the mean over the non-reference
cameras of each one's 6-dof chi-square of its error under its covariance over 6 (1 when the
covariance is honest), the corners' a-posteriori sigma, the model the self-calibration chose
and the range over cameras of the edge offset the bundle estimated (``bundle.edge_offset``:
what it took out of the corners plus what the residuals still read).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.depth.information import tangent_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.solve.edge_offset import without_offset
from rgbd_calib.synth.render import load_ground_truth

DETECTIONS = "detections.json"


def shifted_outward(corners: np.ndarray, offset_px: float) -> np.ndarray:
    """Marker quads ``(N, 4, 2)`` with every edge moved outward by ``offset_px``: each corner
    by the offset along the outward unit normals of its two edges (exact for a square); the
    inverse of the bundle's own correction, :func:`~rgbd_calib.solve.edge_offset.
    without_offset`."""
    return without_offset(corners, -offset_px)


def write_offset_cache(source: Path, target: Path, offset_px: float) -> None:
    """A copy of the detection cache ``source`` with every marker's edges moved outward."""
    target.mkdir(parents=True, exist_ok=True)
    data = json.loads((source / DETECTIONS).read_text())
    for image in data["images"].values():
        det = image["det"]
        if det.get("corners_px"):
            det["corners_px"] = shifted_outward(np.asarray(det["corners_px"], float),
                                                offset_px).tolist()
    (target / DETECTIONS).write_text(json.dumps(data))


def measure(render: Path, cache: Path, mode: str = "auto") -> dict[str, object]:
    """Calibrate ``render`` from ``cache`` with ``bundle.edge_offset: mode``; its errors
    against the truth."""
    config = CalibrationConfig.model_validate({"refine": "none",
                                               "bundle": {"edge_offset": mode}})
    res = calibrate(FolderDataset(render), thesis_board(), config, cache_dir=cache)
    gt = load_ground_truth(render)
    errors, chi2 = [], []
    for name, cam in res.extrinsics.cameras.items():
        if name == res.extrinsics.reference:
            continue
        errors.append(transform_error(cam.T_ref_cam, gt.T_ref_cam[name])[1])
        xi = tangent_error(cam.T_ref_cam, gt.T_ref_cam[name])
        chi2.append(float(xi @ np.linalg.solve(cam.covariance, xi)))
    chosen = res.self_calibration.chosen.name if res.self_calibration is not None else "-"
    read = [e.offset_px for e in res.bundle.edge_offset.values()]
    applied = sum(1 for e in res.bundle.edge_offset.values() if e.applied_px)
    return {"worst_mm": max(errors), "chi2_over_6": float(np.mean(chi2)) / 6,
            "corner_sigma_px": res.bundle.pixel_sigma_estimated, "model": chosen,
            "edge_offsets": read, "modelled": applied,
            "edge_offset_px": f"{min(read):+.4f}..{max(read):+.4f} px" if read else "-"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("render", type=Path,
                        help="a render of `rgbd-calib synth` (with ground_truth.yaml)")
    parser.add_argument("--offsets", type=float, nargs="+", default=[0.0, 0.05, 0.1],
                        help="edge offsets to put into the detections, px per edge "
                        "(default: 0 0.05 0.1)")
    parser.add_argument("--edge-offset", nargs="+", choices=["auto", "off"],
                        default=["auto", "off"],
                        help="bundle.edge_offset modes to calibrate with (default: both)")
    parser.add_argument("--work", type=Path, default=None,
                        help="folder for the detection caches (default: a new temporary one)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="edge_offset_"))
    base = work / "cache"
    measure(args.render, base)  # fills the detection cache
    for offset in args.offsets:
        target = work / f"offset_{offset:g}"
        shutil.rmtree(target, ignore_errors=True)
        write_offset_cache(base, target, offset)
        for mode in args.edge_offset:
            row = measure(args.render, target, mode)
            print(f"edge offset {offset:+.3f} px, {mode}: worst {row['worst_mm']:.3f} mm, "
                  f"chi2/6 {row['chi2_over_6']:.2f}, corner sigma "
                  f"{row['corner_sigma_px']:.3f} px, model {row['model']}, edge offset "
                  f"{row['edge_offset_px']} ({row['modelled']} cameras modelled)", flush=True)


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
