"""Marker-corner bias and scatter of each corner method on real photos of a ChArUco board,
against its saddle corners (docs/accuracy.md, "Corners on real photos"; issue 16).

    python tools/real_corner_bias.py [--data DIR] [--step 1] [--cameras 0,1,2,3] [--json OUT]

Reads every ``--step``-th frame of ``DIR/cam_<i>.mp4`` (Caliscope's 4-webcam session: an
inverted 4 x 5 ChArUco print, ``configs/board_charuco_caliscope.yaml``). Per frame: the saddle
corners, refined (``--reference``, default the project's "painted"), are the reference; the
board's ArUco markers are detected on the inverted image with each corner method
(``--methods``; ``edges`` is the project's edge fit, ``edges_dist`` the same bent by the lens
distortion, ``subpix``/``contour``/``none`` OpenCV's). The printed (design) corners of each
marker are mapped into the image by a homography fitted, in pixels undistorted with Caliscope's
intrinsics (``camera_array.toml``), to the saddle corners within ``--radius`` squares of the
marker (``--plane image``: in raw pixels), and mapped back to image pixels; each detected
corner minus that prediction is split into the outward edge normal and the tangent
(:mod:`rgbd_calib.detect.corner_bias`). Only markers every method found and the reference could
predict are compared, so every method is measured on the same corners.

Also: the reference's own floor (each saddle corner predicted from its neighbours), the
edge fit's fallbacks (markers with a corner it did not set: those get OpenCV's SUBPIX corner),
the views the per-view PnP (default ``PoseConfig``) keeps per method, and the board pose from
each method's markers against the pose from the saddle corners (Caliscope's intrinsics).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rgbd_calib.core.camera import CameraIntrinsics  # noqa: E402
from rgbd_calib.core.config import DetectionConfig, PoseConfig  # noqa: E402
from rgbd_calib.core.geometry import covariance_sigmas, transform_error  # noqa: E402
from rgbd_calib.detect import edge_fit  # noqa: E402
from rgbd_calib.detect.corner_bias import (  # noqa: E402
    BiasSummary,
    corner_components,
    predict_local,
    saddle_self_consistency,
)
from rgbd_calib.detect.markers import (  # noqa: E402
    MarkerDetections,
    detect_charuco,
    detect_markers,
    detect_saddles,
)
from rgbd_calib.model.board import Board, charuco_saddles, marker_board  # noqa: E402
from rgbd_calib.model.board_file import load_board  # noqa: E402
from rgbd_calib.solve.pose import BoardObservation, estimate_board_pose  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "caliscope-charuco-4cam"
BOARD = ROOT / "configs" / "board_charuco_caliscope.yaml"
METHODS = ("edges", "edges_dist", "subpix", "contour", "none")
RADIUS_SQUARES = 2.0  # saddles within this many squares (Chebyshev) of the marker's centre
LOOSE_POSE = PoseConfig(max_reprojection_rms_px=1e3)  # the pose error of every method
MIN_SADDLES = 6  # a local homography from at least this many (8 unknowns, 2 per corner)
EDGE_TESTS = ("contrast", "inliers", "offset", "blur_floor", "blur_cap", "residual")


def caliscope_intrinsics(path: Path) -> dict[int, CameraIntrinsics]:
    """Caliscope's per-camera K and OpenCV distortion (``camera_array.toml``)."""
    raw = tomllib.loads(path.read_text())["cameras"]
    out = {}
    for key, c in raw.items():
        K = np.asarray(c["matrix"], float)
        w, h = c["size"]
        out[int(key)] = CameraIntrinsics(int(w), int(h), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                                         tuple(float(v) for v in c["distortions"]))
    return out


def video_frames(path: Path, step: int = 1, frames: list[int] | None = None):
    """``(index, BGR image)`` of every ``step``-th frame of a video (or only ``frames``)."""
    cap = cv2.VideoCapture(str(path))
    k = 0
    try:
        while True:
            ok, image = cap.read()
            if not ok:
                return
            if (frames is None and k % step == 0) or (frames is not None and k in frames):
                yield k, image
            k += 1
    finally:
        cap.release()


def _method_config(method: str) -> tuple[DetectionConfig, bool]:
    """The detection config of a method and whether it uses the lens distortion."""
    if method == "edges_dist":
        return DetectionConfig(refinement="edges"), True
    return DetectionConfig(refinement=method), False


class EdgeTestLog:
    """The edge fit's tests (``edge_fit._edge_tests``, by name, ``(M,4)``) of its last pass
    in the ``with`` block: why edges fell back to SUBPIX."""

    def __enter__(self) -> EdgeTestLog:
        self.last: dict[str, np.ndarray] | None = None
        self._tests = edge_fit._edge_tests

        def spy(*args, **kwargs):
            self.last = self._tests(*args, **kwargs)
            return self.last

        edge_fit._edge_tests = spy
        return self

    def __exit__(self, *exc) -> None:
        edge_fit._edge_tests = self._tests


@dataclass
class ViewResult:
    """One frame of one camera: the compared corners' errors per method and the bookkeeping."""

    camera: int
    frame: int
    saddles: int
    saddle_loo_px: np.ndarray  # (J,2) leave-one-out residuals of the saddle reference
    normal: dict[str, np.ndarray] = field(default_factory=dict)  # method -> (N,4) px
    tangent: dict[str, np.ndarray] = field(default_factory=dict)
    error: dict[str, np.ndarray] = field(default_factory=dict)  # method -> (N,4,2) px
    edge_set: np.ndarray | None = None  # (N,4) True where the edge fit set the compared corner
    size_px: np.ndarray | None = None  # (N,) each compared marker's mean corner-to-centre px
    markers: dict[str, int] = field(default_factory=dict)  # found per method
    edge_markers_partial: int = 0  # markers with 1-3 corners set by the edge fit
    edge_markers_none: int = 0  # markers with no corner set by the edge fit
    edge_failed: dict[str, int] = field(default_factory=dict)  # edges failing each test
    edges_tested: int = 0
    pose_kept: dict[str, str] = field(default_factory=dict)  # method -> "" or reject reason
    pose_error: dict[str, tuple[float, float]] = field(default_factory=dict)  # (deg, mm)
    saddle_pose: str = ""  # "" or why the saddle quads gave no pose
    # translation difference to the saddle pose over its claimed sigma (both poses' sigmas)
    pose_z: dict[str, float] = field(default_factory=dict)


def measure_view(
    image: np.ndarray,
    board: Board,
    markers: Board,
    intrinsics: CameraIntrinsics,
    methods: tuple[str, ...] = METHODS,
    reference: str = "painted",
    plane: str = "undistorted",
    radius_squares: float = RADIUS_SQUARES,
    camera: int = 0,
    frame: int = 0,
) -> ViewResult | None:
    """Every method's marker corners against the saddle reference in one BGR image (None
    when no saddle corner is found)."""
    spec = board.charuco
    ids, px = detect_saddles(image, board, corners=reference)
    if len(ids) < MIN_SADDLES:
        return None
    saddle_xy = charuco_saddles(spec, board.dictionary)[ids, :2]
    if plane == "undistorted":
        und, dis = intrinsics.undistort_pixels, intrinsics.distort_pixels
    else:
        und = dis = np.asarray
    radius_m = radius_squares * spec.square_length
    loo = saddle_self_consistency(saddle_xy, px, radius_m, MIN_SADDLES, und, dis)
    out = ViewResult(camera, frame, len(ids), loo)
    inverted = 255 - image if spec.inverted else image
    dets: dict[str, MarkerDetections] = {}
    for m in methods:
        config, bent = _method_config(m)
        with EdgeTestLog() as log:
            dets[m] = detect_markers(inverted, markers, config, intrinsics if bent else None)
        out.markers[m] = len(dets[m])
        if m == "edges" and log.last is not None:
            out.edges_tested = int(next(iter(log.last.values())).size)
            out.edge_failed = {k: int((~v).sum()) for k, v in log.last.items()}
    if "edges" in dets:
        n_set = dets["edges"].refined.sum(axis=1)
        out.edge_markers_partial = int(np.sum((n_set > 0) & (n_set < 4)))
        out.edge_markers_none = int(np.sum(n_set == 0))
    # the markers every method found, each predicted by the saddles around it
    common = set.intersection(*(set(d.ids.tolist()) for d in dets.values()))
    predicted = {}
    for i in sorted(common):
        design = markers.corners[markers.index_of[i], :, :2]
        p = predict_local(saddle_xy, px, design, radius_m, MIN_SADDLES, und, dis)
        if p is not None:
            predicted[i] = p
    keep = sorted(predicted)
    pred = np.array([predicted[i] for i in keep]).reshape(-1, 4, 2)
    out.size_px = np.linalg.norm(pred - pred.mean(axis=1, keepdims=True), axis=-1).mean(axis=1)
    for m, d in dets.items():
        rows = [int(np.nonzero(d.ids == i)[0][0]) for i in keep]
        measured = d.corners_px[rows].reshape(-1, 4, 2)
        out.normal[m], out.tangent[m] = corner_components(measured, pred)
        out.error[m] = measured - pred
        if m == "edges":
            out.edge_set = d.refined[rows].reshape(-1, 4)
    # per-view pose: each method's markers vs the saddle quads (Caliscope's intrinsics)
    ref = estimate_board_pose(detect_charuco(image, board, corners=reference), board,
                              intrinsics, PoseConfig())
    out.saddle_pose = "" if isinstance(ref, BoardObservation) else ref.reason
    for m, d in dets.items():
        obs = estimate_board_pose(d, markers, intrinsics, PoseConfig())
        out.pose_kept[m] = "" if isinstance(obs, BoardObservation) else obs.reason
        if isinstance(obs, BoardObservation) and isinstance(ref, BoardObservation):
            mm = transform_error(obs.T_cam_board, ref.T_cam_board)[1]
            sigma_mm = np.hypot(covariance_sigmas(obs.covariance)[1],
                                covariance_sigmas(ref.covariance)[1])
            out.pose_z[m] = mm / sigma_mm
        # the pose error without the RMS gate, so that every method is compared on one set
        obs = estimate_board_pose(d, markers, intrinsics, LOOSE_POSE)
        if isinstance(obs, BoardObservation) and isinstance(ref, BoardObservation):
            out.pose_error[m] = transform_error(obs.T_cam_board, ref.T_cam_board)
    return out


def pose_reasons(image: np.ndarray, board: Board, markers: Board,
                 intrinsics: CameraIntrinsics, methods: tuple[str, ...]) -> dict[str, str]:
    """Per method, "" when the per-view PnP (default ``PoseConfig``) keeps the frame, else
    why not: for the frames that are not views (too few saddle corners to compare)."""
    inverted = 255 - image if board.charuco.inverted else image
    out = {}
    for m in methods:
        config, bent = _method_config(m)
        det = detect_markers(inverted, markers, config, intrinsics if bent else None)
        obs = estimate_board_pose(det, markers, intrinsics, PoseConfig())
        out[m] = "" if isinstance(obs, BoardObservation) else obs.reason
    return out


def run(data: Path, cameras: list[int], step: int = 1, frames: list[int] | None = None,
        every_frame: list | None = None, **kwargs) -> list[ViewResult]:
    """The views of the given cameras' frames; with ``every_frame`` (a list), also appends
    ``(camera, frame, {method: PnP reject reason or ""})`` for every frame read."""
    board = load_board(BOARD)
    markers = marker_board(board)
    intrinsics = caliscope_intrinsics(data / "camera_array.toml")
    views = []
    for cam in cameras:
        for k, image in video_frames(data / f"cam_{cam}.mp4", step, frames):
            v = measure_view(image, board, markers, intrinsics[cam], camera=cam, frame=k,
                             **kwargs)
            if v is not None:
                views.append(v)
            if every_frame is not None:
                reasons = dict(v.pose_kept) if v is not None else pose_reasons(
                    image, board, markers, intrinsics[cam],
                    kwargs.get("methods", METHODS))
                every_frame.append((cam, k, reasons))
    return views


def every_frame_summary(rows: list, methods: tuple[str, ...]) -> dict:
    """PnP on every frame read: per method the frames it keeps and those it rejects as
    too_few_markers while another method keeps them."""
    return {m: {"frames": len(rows),
                "kept": sum(r[m] == "" for _, _, r in rows),
                "too_few_kept_by_another": sum(
                    r[m] == "too_few_markers" and any(v == "" for v in r.values())
                    for _, _, r in rows)}
            for m in methods}


def summarise(views: list[ViewResult], methods: tuple[str, ...]) -> dict:
    """Per camera and overall ("all"): views, corner bias/scatter per method, the saddle
    reference's floor, the edge fit's fallbacks, views kept by the PnP and pose errors."""
    out: dict = {}
    groups = {str(c): [v for v in views if v.camera == c] for c in sorted({v.camera
                                                                          for v in views})}
    groups["all"] = views
    for g, vs in groups.items():
        loo = np.concatenate([v.saddle_loo_px for v in vs]) if vs else np.zeros((0, 2))
        entry = {
            "views": len(vs),
            "saddle_floor": {"corners": len(loo),
                             "bias_x_px": float(loo[:, 0].mean()) if len(loo) else None,
                             "bias_y_px": float(loo[:, 1].mean()) if len(loo) else None,
                             "rms_px": float(np.sqrt((loo**2).sum(1).mean())) if len(loo)
                             else None},
            "edge_fallback": {"markers": int(sum(v.markers.get("edges", 0) for v in vs)),
                              "partial": int(sum(v.edge_markers_partial for v in vs)),
                              "none": int(sum(v.edge_markers_none for v in vs)),
                              "views_none_set": int(sum(
                                  v.edge_markers_none == v.markers.get("edges", 0) > 0
                                  for v in vs)),
                              "edges_tested": int(sum(v.edges_tested for v in vs)),
                              "edges_failed": {k: int(sum(v.edge_failed.get(k, 0) for v in vs))
                                               for k in EDGE_TESTS}},
            "methods": {},
        }
        # poses on the views every method and the saddle reference solved
        both = [v for v in vs if all(m in v.pose_error for m in methods)]
        entry["pose_views_compared"] = len(both)
        for m in _rows(methods):
            entry["methods"][m] = asdict(_summary(vs, m))
            if m not in methods:
                continue
            reasons: dict[str, int] = {}
            for v in vs:
                r = v.pose_kept.get(m, "") or "kept"
                reasons[r] = reasons.get(r, 0) + 1
            pe = np.array([v.pose_error[m] for v in both]).reshape(-1, 2)
            z = [v.pose_z[m] for v in vs if m in v.pose_z]
            entry["methods"][m].update({
                "pose_views": reasons,
                # views this method keeps and the edge fit does not
                "kept_lost_by_edges": int(sum(not v.pose_kept.get(m, "x")
                                              and bool(v.pose_kept.get("edges", "")) for v in vs)),
                "pose_z_median": float(np.median(z)) if z else None,
                "pose_deg_median": float(np.median(pe[:, 0])) if len(pe) else None,
                "pose_mm_median": float(np.median(pe[:, 1])) if len(pe) else None,
                "pose_mm_p90": float(np.percentile(pe[:, 1], 90)) if len(pe) else None,
            })
        reasons = {}
        for v in vs:
            r = v.saddle_pose or "kept"
            reasons[r] = reasons.get(r, 0) + 1
        entry["saddle_pose_views"] = reasons
        out[g] = entry
    return out


def size_fit(views: list[ViewResult], method: str, marker_length_m: float) -> dict:
    """Per camera: its markers' normal bias (mean over their corners, px) fitted to a constant
    plus an ink spread times the marker's px per metre (``2 size / marker length``): a bias
    constant in px (the imaging) against one that grows with the marker's size in the image
    (as a print's ink spread would), each with its standard error; markers beyond 5 robust
    sigmas of the camera's median left out."""
    out = {}
    for cam in sorted({v.camera for v in views}):
        vs = [v for v in views if v.camera == cam and method in v.normal and v.size_px is not None]
        if not vs:
            continue
        n = np.concatenate([v.normal[method].mean(axis=1) for v in vs])
        g = 2 * np.concatenate([v.size_px for v in vs]) / marker_length_m
        ok = np.isfinite(n) & np.isfinite(g)
        n, g = n[ok], g[ok]
        mad = 1.4826 * np.median(np.abs(n - np.median(n)))
        k = np.abs(n - np.median(n)) <= 5 * mad if mad > 0 else np.ones(n.size, bool)
        n, g = n[k], g[k]
        if n.size < 4:
            continue
        A = np.column_stack([np.ones_like(g), g])
        x = np.linalg.lstsq(A, n, rcond=None)[0]
        se = np.sqrt(np.diag(np.linalg.inv(A.T @ A)) * np.sum((n - A @ x) ** 2) / (n.size - 2))
        out[cam] = {"markers": int(n.size), "constant_px": float(x[0]),
                    "constant_se_px": float(se[0]), "spread_mm": 1000 * float(x[1]),
                    "spread_se_mm": 1000 * float(se[1]),
                    "size_px_median": float(np.median(g) * marker_length_m / 2)}
    return out


def _rows(methods: tuple[str, ...]) -> tuple[str, ...]:
    """The table's rows: each method, and "edges:set" (only the corners the edge fit set;
    the pose stage drops a marker with any other, ``PoseConfig.use_unrefined_corners``)."""
    return methods + (("edges:set",) if "edges" in methods else ())


def _summary(vs: list[ViewResult], row: str) -> BiasSummary:
    m, only_set = row.split(":")[0], row.endswith(":set")
    pick = [(v.normal[m], v.tangent[m], v.error[m],
             v.edge_set if only_set else np.ones(v.normal[m].shape, bool)) for v in vs]
    if not pick:
        return BiasSummary.of(np.zeros(0), np.zeros(0), np.zeros((0, 2)))
    return BiasSummary.of(np.concatenate([n[k] for n, _, _, k in pick]),
                          np.concatenate([t[k] for _, t, _, k in pick]),
                          np.concatenate([e[k] for _, _, e, k in pick]))


def print_tables(summary: dict, methods: tuple[str, ...]) -> None:
    print("| camera | method | views | corners | normal bias (px) | normal scatter (px) | "
          "tangent bias (px) | tangent scatter (px) | RMS (px) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for g, e in summary.items():
        for m in _rows(methods):
            s = e["methods"][m]
            print(f"| {g} | {m} | {e['views']} | {s['corners']} | {s['normal_bias_px']:+.3f} | "
                  f"{s['normal_scatter_px']:.3f} | {s['tangent_bias_px']:+.3f} | "
                  f"{s['tangent_scatter_px']:.3f} | {s['rms_px']:.3f} |")
    print("\n| camera | saddle corners (LOO) | bias x / y (px) | RMS (px) |")
    print("|---|---|---|---|")
    for g, e in summary.items():
        f = e["saddle_floor"]
        print(f"| {g} | {f['corners']} | {f['bias_x_px']:+.3f} / {f['bias_y_px']:+.3f} | "
              f"{f['rms_px']:.3f} |")
    print("\n| camera | edge-fit markers | partly SUBPIX | all SUBPIX | views with no corner "
          "set | edges tested | failed: " + " / ".join(EDGE_TESTS) + " |")
    print("|---|---|---|---|---|---|---|")
    for g, e in summary.items():
        fb = e["edge_fallback"]
        failed = " / ".join(str(fb["edges_failed"][k]) for k in EDGE_TESTS)
        print(f"| {g} | {fb['markers']} | {fb['partial']} | {fb['none']} | "
              f"{fb['views_none_set']} | {fb['edges_tested']} | {failed} |")
    print("\n| camera | method | PnP views kept, default gates (rejected: reason) | kept, "
          "lost by edges | rotation median (deg) | translation median / p90 (mm) | "
          "error / claimed sigma, median |")
    print("|---|---|---|---|---|---|---|")
    for g, e in summary.items():
        sad = e["saddle_pose_views"]
        rej = ", ".join(f"{r} {n}" for r, n in sad.items() if r != "kept")
        print(f"| {g} | saddles | {sad.get('kept', 0)} ({rej or '-'}) | | reference | "
              f"reference | |")
        for m in methods:
            s = e["methods"][m]
            kept = s["pose_views"].get("kept", 0)
            rej = ", ".join(f"{r} {n}" for r, n in s["pose_views"].items() if r != "kept")
            z = "-" if s["pose_z_median"] is None else f"{s['pose_z_median']:.1f}"
            lost = s["kept_lost_by_edges"] if m != "edges" else ""
            if s["pose_deg_median"] is None:
                print(f"| {g} | {m} | {kept} ({rej or '-'}) | {lost} | - | - | {z} |")
                continue
            print(f"| {g} | {m} | {kept} ({rej or '-'}) | {lost} | {s['pose_deg_median']:.3f} "
                  f"| {s['pose_mm_median']:.2f} / {s['pose_mm_p90']:.2f} | {z} |")
        print(f"| {g} | (views compared) | {e['pose_views_compared']} | | | | |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--cameras", default="0,1,2,3")
    ap.add_argument("--step", type=int, default=1, help="every step-th frame")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--reference", default="painted", choices=("painted", "subpix", "opencv"))
    ap.add_argument("--plane", default="undistorted", choices=("undistorted", "image"))
    ap.add_argument("--radius", type=float, default=RADIUS_SQUARES,
                    help="saddles within this many squares of a marker fit its homography")
    ap.add_argument("--json", type=Path, help="write the summary here")
    ap.add_argument("--by-size", action="store_true",
                    help="also fit each camera's edge-fit bias to a constant plus an ink spread "
                    "growing with the marker's size in the image")
    args = ap.parse_args()
    methods = tuple(args.methods.split(","))
    t0 = time.perf_counter()
    every: list = []
    views = run(args.data, [int(c) for c in args.cameras.split(",")], args.step,
                every_frame=every, methods=methods, reference=args.reference,
                plane=args.plane, radius_squares=args.radius)
    summary = summarise(views, methods)
    print_tables(summary, methods)
    summary["every_frame"] = every_frame_summary(every, methods)
    print("\n| method | frames | PnP keeps | too_few_markers, kept by another method |")
    print("|---|---|---|---|")
    for m, e in summary["every_frame"].items():
        print(f"| {m} | {e['frames']} | {e['kept']} | {e['too_few_kept_by_another']} |")
    if args.by_size and "edges" in methods:
        length = marker_board(load_board(BOARD)).marker_length
        summary["by_size"] = size_fit(views, "edges", length)
        print("\n| camera | markers | median size (px) | constant (px) | ink spread (mm) |")
        print("|---|---|---|---|---|")
        for c, e in summary["by_size"].items():
            print(f"| {c} | {e['markers']} | {e['size_px_median']:.1f} | {e['constant_px']:+.3f} "
                  f"+- {e['constant_se_px']:.3f} | {e['spread_mm']:+.3f} +- "
                  f"{e['spread_se_mm']:.3f} |")
    print(f"\n{len(views)} views, {time.perf_counter() - t0:.0f} s")
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "summary": summary}, indent=1))


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
