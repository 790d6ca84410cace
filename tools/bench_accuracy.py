"""Accuracy benchmark on synthetic rigs with ground truth: ours against the peers.

    python tools/bench_accuracy.py --data bench_data --seeds 0 1 2 --md docs/accuracy.md \
        --sweep noise frames depth-bias

Renders every layout x seed once with the synth defaults (cached under ``--data``; an existing
render is reused), runs every method on the same images and compares each camera's
``T_ref_cam`` with ``ground_truth.yaml``. Writes the raw results (``--json``: every run with
every camera's errors and claimed sigmas), the markdown tables (stdout and ``--md``) and plots
(``--img``). ``--from-json`` re-makes the tables and plots from a saved JSON without running
anything (a JSON without sweeps or race16 simply has no such tables).

Layouts (``--layouts``): ``race`` (8 cameras), ``race16`` (16 cameras, two tiers, reference
``left_lo1``), both 848x480; ``ring`` (6) and ``thesis-line`` (4), both 1280x720.

Sweeps (``--sweep noise frames depth-bias``), each on ``--sweep-layout`` (race) and the
``--seeds``, every other setting at the synth defaults (``--frames`` frame sets, blur 0.6 px,
colour noise 2 DN, no depth bias); every point is its own rendered set, named after what
differs from the defaults (``race-f40-s0-noise5``, ``race-f80-s0``, ``race-f40-s0-bias0.006``)
so it is rendered once and shared with the main grid where they coincide:

- ``noise``: image noise ``SynthParams.color_noise_dn`` (DN, 1-sigma) at ``--noise-levels``;
- ``frames``: frame sets per rig at ``--frame-counts``;
- ``depth-bias``: ``SynthParams.depth_bias`` (each camera's depth scale off by up to +-this,
  relative) at ``--bias-levels``: only the depth method can see it. The board-only methods
  should not change beyond the scatter between sets: synth draws the biases from the stream
  that also draws the intrinsics, so a biased set has slightly different intrinsics (exact
  and known to every method) but the same camera and board poses.

Methods (``--methods``; same images, intrinsics fixed to the rig's):

- ``thesis``: the seed thesis's pipeline (tools/peers.py): OpenCV's unrefined corners, per-view
  PnP, pose graph with one isotropic edge noise, plain least squares.
- ``opencv-*``: ``cv2.calibrateMultiview`` (OpenCV 5) on our SUBPIX or edge-fit detections.
- ``posegraph-*``: ours, ``CalibrationConfig(method="posegraph")`` (PnP-covariance weighted,
  robust), with ``DetectionConfig(refinement="subpix")`` or ``"edges"``.
- ``bundle-*``: ours, joint bundle adjustment on the corners (the default), same two corners;
  board only (``refine="none"``: the depth stage is left out).
- ``bundle-edges-depth``: ours with the depth stage, ``refine="colored-icp"`` (depth-scale
  estimate per camera, colored ICP of overlapping camera pairs, joint adjustment); ~1.5 s per
  camera pair at 848x480.

Detections are cached per set and corner refinement, and each method's result per set under
``--data/cache/<set>/results/`` (keyed by the method, the set and a hash of the package
modules the methods use and tools/peers.py, so a code change re-runs them; ``--rerun``
ignores the cache). A run that stops half way, or a second command with more layouts or
sweeps, only computes what is missing.

Errors are over the non-reference cameras (the reference is the gauge: exact by definition).
The uncertainty check divides each camera's error by the sigma the method claims for it
(``sigma_translation_mm`` / ``sigma_rotation_deg``, 1-sigma along the worst axis) and takes the
RMS over seeds and cameras; honest sigmas give 0.5-2 (1 for an error along the worst axis,
sqrt(3) for an isotropic one). ``NEES`` is the stricter check with the full 6x6 covariance:
RMS of sqrt(xi^T C^-1 xi / 6), ``T_true = T_est Exp(xi)``, 1 when the covariance is right.
Acceptance (issue 3, ``bundle-edges``): within the layout's bound on every camera, more
accurate than every peer (worst and median) and a worst-camera error at least 3x lower than
the best peer's that succeeded on every seed, normalised error RMS 0.5-2.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/peers.py

from peers import opencv_multiview, thesis_method  # noqa: E402

from rgbd_calib.core.config import CalibrationConfig, DetectionConfig
from rgbd_calib.core.geometry import matrix_to_rotvec, transform_error  # noqa: E402
from rgbd_calib.core.yamlio import atomic_write_text, read_yaml_mapping  # noqa: E402
from rgbd_calib.detect.run import detect_dataset  # noqa: E402
from rgbd_calib.model.board import Board, thesis_board  # noqa: E402
from rgbd_calib.model.dataset import FolderDataset  # noqa: E402
from rgbd_calib.pipelines.calibrate import calibrate  # noqa: E402
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize  # noqa: E402

LAYOUTS = ("race", "race16", "ring", "thesis-line")
RESOLUTION = {"race": "848x480", "race16": "848x480", "ring": "1280x720", "thesis-line": "1280x720"}
# Acceptance bounds of issue 3 (every camera): rotation (deg), translation (mm).
BOUNDS = {
    "race": (0.1, 1.0),
    "race16": (0.1, 1.0),
    "ring": (0.05, 0.5),
    "thesis-line": (0.05, 0.5),
}
NORMALISED_RMS_RANGE = (0.5, 2.0)
PEER_MARGIN = 3.0  # ours' worst camera at least this many times better than the best peer's
OURS = "bundle-edges"
# A run that returns poses this far off (or with this reprojection RMS) has failed outright.
DIVERGED_MM, DIVERGED_DEG, DIVERGED_RMS_PX = 100.0, 5.0, 10.0
MD_BEGIN, MD_END = "<!-- bench_accuracy:begin -->", "<!-- bench_accuracy:end -->"


@dataclass(frozen=True)
class Method:
    key: str
    label: str
    kind: str  # "thesis" | "opencv" | "ours"
    refinement: str
    final: str = ""  # ours: "posegraph" | "bundle"
    refine: str = "none"  # ours: CalibrationConfig.refine (the depth stage)


METHODS = (
    Method("thesis", "thesis: PnP + plain pose graph, OpenCV corners", "thesis", "none"),
    Method("opencv-subpix", "OpenCV calibrateMultiview, SUBPIX corners", "opencv", "subpix"),
    Method("opencv-edges", "OpenCV calibrateMultiview, edge corners", "opencv", "edges"),
    Method("posegraph-subpix", "ours: pose graph, SUBPIX corners", "ours", "subpix", "posegraph"),
    Method("posegraph-edges", "ours: pose graph, edge corners", "ours", "edges", "posegraph"),
    Method("bundle-subpix", "ours: bundle adjustment, SUBPIX corners", "ours", "subpix", "bundle"),
    Method(
        "bundle-edges", "ours: bundle adjustment, edge corners (default)", "ours", "edges", "bundle"
    ),
    Method(
        "bundle-edges-depth",
        "ours: bundle adjustment + depth stage (colored ICP), edge corners",
        "ours",
        "edges",
        "bundle",
        "colored-icp",
    ),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}
# one matplotlib colour per method in every plot (ours red, ours + depth green)
COLOUR = {
    "thesis": "C0",
    "opencv-subpix": "C1",
    "opencv-edges": "C8",
    "posegraph-subpix": "C5",
    "posegraph-edges": "C4",
    "bundle-subpix": "C7",
    "bundle-edges": "C3",
    "bundle-edges-depth": "C2",
}
SYNTH_DEFAULTS = SynthParams()


@dataclass(frozen=True)
class Sweep:
    """One setting varied on one layout, everything else at the synth defaults."""

    key: str  # CLI name
    field: str  # "frames" or the DatasetSpec / SynthParams field
    title: str
    unit: str  # appended to a level in the tables


SWEEPS = {
    "noise": Sweep("noise", "color_noise_dn", "image noise (colour noise sigma, DN)", " DN"),
    "frames": Sweep("frames", "frames", "number of frame sets", " frames"),
    "depth-bias": Sweep(
        "depth-bias", "depth_bias", "depth-scale bias (max relative error per camera)", ""
    ),
}


# ----------------------------------------------------------------------------- data
@dataclass(frozen=True)
class DatasetSpec:
    """A rendered set: layout, frame sets, seed and the synth settings the sweeps vary."""

    layout: str
    frames: int
    seed: int
    color_noise_dn: float = SYNTH_DEFAULTS.color_noise_dn
    depth_bias: float = SYNTH_DEFAULTS.depth_bias

    @property
    def name(self) -> str:
        """``race-f40-s0``, plus a suffix per setting that differs from the synth defaults."""
        name = dataset_name(self.layout, self.frames, self.seed)
        if self.color_noise_dn != SYNTH_DEFAULTS.color_noise_dn:
            name += f"-noise{self.color_noise_dn:g}"
        if self.depth_bias != SYNTH_DEFAULTS.depth_bias:
            name += f"-bias{self.depth_bias:g}"
        return name

    def params(self) -> SynthParams:
        return replace(
            SYNTH_DEFAULTS, color_noise_dn=self.color_noise_dn, depth_bias=self.depth_bias
        )

    def fields(self) -> dict[str, Any]:
        return {
            "layout": self.layout,
            "seed": self.seed,
            "frames": self.frames,
            "dataset": self.name,
            "color_noise_dn": self.color_noise_dn,
            "depth_bias": self.depth_bias,
        }


def dataset_name(layout: str, frames: int, seed: int) -> str:
    return f"{layout}-f{frames}-s{seed}"


def ensure_dataset(data: Path, spec: DatasetSpec, board: Board, workers: int) -> Path:
    """The rendered set, rendering it when ``ground_truth.yaml`` is missing; an existing set
    must have been rendered with the settings its name claims."""
    path = data / spec.name
    gt_path = path / "ground_truth.yaml"
    if gt_path.is_file():
        saved = read_yaml_mapping(gt_path, "ground truth").get("params", {})
        for key, want in (("color_noise_dn", spec.color_noise_dn), ("depth_bias", spec.depth_bias)):
            if key in saved and not math.isclose(float(saved[key]), want, abs_tol=1e-12):
                raise SystemExit(f"{path}: rendered with {key}={saved[key]}, expected {want}")
        return path
    print(f"rendering {path} ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    synthesize(path, spec.layout, spec.frames, spec.seed, board, spec.params(), workers=workers)
    print(f"  rendered in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return path


# ----------------------------------------------------------------------------- errors
def camera_record(
    name: str,
    T_est: np.ndarray,
    T_true: np.ndarray,
    sigma_rotation_deg: float | None = None,
    sigma_translation_mm: float | None = None,
    covariance: np.ndarray | None = None,
) -> dict[str, Any]:
    """Error of one ``T_ref_cam`` (deg, mm) and, when the method claims one, its uncertainty.

    ``nees`` is ``xi^T C^-1 xi`` with ``T_true = T_est Exp(xi)``, ``xi = [omega, v]`` in the
    camera (body) frame, GTSAM's order, to first order in the (tiny) error."""
    rot_deg, trans_mm = transform_error(T_est, T_true)
    rec: dict[str, Any] = {
        "camera": name,
        "rotation_deg": rot_deg,
        "translation_mm": trans_mm,
        "sigma_rotation_deg": _finite(sigma_rotation_deg),
        "sigma_translation_mm": _finite(sigma_translation_mm),
        "nees": None,
    }
    if covariance is not None and np.all(np.isfinite(covariance)) and np.any(covariance):
        R_est = T_est[:3, :3]
        xi = np.concatenate(
            [matrix_to_rotvec(R_est.T @ T_true[:3, :3]), R_est.T @ (T_true[:3, 3] - T_est[:3, 3])]
        )
        try:
            rec["nees"] = float(xi @ np.linalg.solve(covariance, xi))
        except np.linalg.LinAlgError:
            pass
    return rec


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) and x > 0 else None


def _run_ours(
    method: Method, dataset: FolderDataset, board: Board, cache: Path, workers: int
) -> tuple[dict[str, Any], dict[str, str], float, Any]:
    # refine="none" for the board-only methods (the default "auto" adds the depth stage,
    # colored ICP, on sets with depth); "colored-icp" for bundle-edges-depth
    config = CalibrationConfig(
        detection=DetectionConfig(refinement=method.refinement),
        method=method.final,
        workers=workers,
        refine=method.refine,
    )
    t0 = time.perf_counter()
    result = calibrate(dataset, board, config, cache_dir=cache)
    # wall time, not the sum of timings_s: the depth stage's last step (finish_pairs) is untimed
    solve_s = time.perf_counter() - t0 - result.timings_s.get("detection", 0.0)
    cams, missing = dict(result.extrinsics.cameras), dict(result.extrinsics.unconnected)
    return cams, missing, solve_s, result.depth


def _depth_summary(depth: Any, gt_scales: dict[str, float]) -> dict[str, Any]:
    """What the depth stage did: pairs registered / accepted, and each camera's depth-scale
    factor (estimate, its sigma, the true one) for the depth-bias sweep."""
    return {
        "pairs": len(depth.pairs),
        "accepted": len(depth.relative_poses),
        "timings_s": dict(depth.timings_s),
        "scales": {
            c: {"factor": e.factor, "sigma": e.sigma, "true": gt_scales.get(c)}
            for c, e in depth.depth_scales.items()
        },
    }


_CODE_HASH: str | None = None


def code_hash() -> str:
    """Hash of the sources the methods run (every ``rgbd_calib`` module this tool has loaded:
    the pipeline has no lazy imports, so cli.py and the like are left out) and
    tools/peers.py: a cached result is only reused with the code that produced it."""
    global _CODE_HASH
    if _CODE_HASH is None:
        files = {Path(__file__).resolve().parent / "peers.py"}
        for name, module in list(sys.modules.items()):
            if name.split(".")[0] == "rgbd_calib" and getattr(module, "__file__", None):
                files.add(Path(module.__file__).resolve())
        h = hashlib.sha256(str(RESULT_CACHE_VERSION).encode())
        for f in sorted(files):
            h.update(f.name.encode() + b"\0" + f.read_bytes())
        _CODE_HASH = h.hexdigest()[:16]
    return _CODE_HASH


RESULT_CACHE_VERSION = 1  # bump when run_method's record changes


def cached_run(
    method: Method, path: Path, board: Board, cache_root: Path, workers: int, rerun: bool = False
) -> tuple[dict[str, Any], bool]:
    """``run_method``, reusing the record saved for this set, method and code (a dict with
    ``fingerprint`` and ``record`` under ``<cache>/<set>/results/<method>.json``).
    Returns the record and whether it came from the cache."""
    gt = (path / "ground_truth.yaml").stat()
    fingerprint = hashlib.sha256(
        json.dumps(
            [method.__dict__, board.to_dict(), code_hash(), gt.st_size, gt.st_mtime_ns],
            sort_keys=True,
            default=str,
        ).encode()
    ).hexdigest()[:16]
    cache_file = cache_root / path.name / "results" / f"{method.key}.json"
    if not rerun and cache_file.is_file():
        try:
            saved = json.loads(cache_file.read_text())
            if saved.get("fingerprint") == fingerprint:
                return saved["record"], True
        except (ValueError, KeyError):
            pass  # a corrupt cache is only a cache
    rec = run_method(method, path, board, cache_root, workers)
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        cache_file, json.dumps({"fingerprint": fingerprint, "record": _rounded(rec)}, indent=0)
    )
    return rec, False


def run_method(
    method: Method, path: Path, board: Board, cache_root: Path, workers: int
) -> dict[str, Any]:
    """One method on one rendered set; never raises (a failure is a record with a message)."""
    dataset = FolderDataset(path)
    gt = load_ground_truth(path)
    cache = cache_root / path.name / method.refinement
    cache.mkdir(parents=True, exist_ok=True)
    rec: dict[str, Any] = {
        "method": method.key,
        "status": "ok",
        "message": "",
        "time_s": None,
        "rms_px": None,
        "cameras": [],
        "missing": {},
    }
    try:
        if method.kind == "opencv":
            detections = detect_dataset(
                dataset,
                board,
                DetectionConfig(refinement=method.refinement),
                cache / "detections.json",
                workers,
            )
            t0 = time.perf_counter()
            mv = opencv_multiview(dataset, board, detections)
            rec["time_s"] = time.perf_counter() - t0
            rec["rms_px"] = mv.rms_px
            poses = {c: (T, None, None, None) for c, T in mv.T_ref_cam.items()}
            missing: dict[str, str] = {}
        else:
            if method.kind == "thesis":
                result = thesis_method(dataset, board, cache_dir=cache, workers=workers)
                cams, missing = dict(result.extrinsics.cameras), dict(result.extrinsics.unconnected)
                rec["time_s"] = sum(v for k, v in result.timings_s.items() if k != "detection")
            else:
                cams, missing, rec["time_s"], depth = _run_ours(
                    method, dataset, board, cache, workers
                )
                if depth is not None:
                    rec["depth"] = _depth_summary(depth, gt.depth_scale_bias)
            poses = {
                c: (e.T_ref_cam, e.sigma_rotation_deg, e.sigma_translation_mm, e.covariance)
                for c, e in cams.items()
            }
    except Exception as exc:  # a peer (or a bug of ours) failing outright is a result
        rec["status"] = "failed"
        rec["message"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
        rec["traceback"] = traceback.format_exc(limit=4)
        return rec
    for c in dataset.cameras:
        if c == gt.reference:
            continue
        if c not in poses:
            rec["missing"][c] = missing.get(c, "not returned")
            continue
        rec["cameras"].append(camera_record(c, poses[c][0], gt.T_ref_cam[c], *poses[c][1:]))
    problems = []
    if rec["missing"]:
        problems.append(
            "not calibrated: " + ", ".join(f"{c} ({r})" for c, r in rec["missing"].items())
        )
    worst_mm = max((r["translation_mm"] for r in rec["cameras"]), default=0.0)
    worst_deg = max((r["rotation_deg"] for r in rec["cameras"]), default=0.0)
    if (
        worst_mm > DIVERGED_MM
        or worst_deg > DIVERGED_DEG
        or (rec["rms_px"] is not None and rec["rms_px"] > DIVERGED_RMS_PX)
    ):
        rms = f"RMS {_px(rec['rms_px'])} px, " if rec["rms_px"] is not None else ""
        problems.append(f"diverged: {rms}worst camera {worst_mm:.0f} mm / {worst_deg:.1f} deg off")
    if problems:
        rec["status"] = "failed"
        rec["message"] = "; ".join(problems)
    return rec


# ----------------------------------------------------------------------------- summaries
def _rms(values: list[float]) -> float | None:
    return float(np.sqrt(np.mean(np.square(values)))) if values else None


def summarise(runs: list[dict[str, Any]], layout: str | None, method: str) -> dict[str, Any]:
    """Worst / median errors, normalised-error RMS and failures of one method (one layout, or
    all layouts with ``layout=None``) over seeds and non-reference cameras of the ok runs."""
    sel = [r for r in runs if r["method"] == method and (layout is None or r["layout"] == layout)]
    ok = [r for r in sel if r["status"] == "ok"]
    cams = [c for r in ok for c in r["cameras"]]
    rot = [c["rotation_deg"] for c in cams]
    trans = [c["translation_mm"] for c in cams]
    ratio_t = [
        c["translation_mm"] / c["sigma_translation_mm"] for c in cams if c["sigma_translation_mm"]
    ]
    ratio_r = [c["rotation_deg"] / c["sigma_rotation_deg"] for c in cams if c["sigma_rotation_deg"]]
    nees = [c["nees"] / 6.0 for c in cams if c["nees"] is not None]
    times = [r["time_s"] for r in ok if r["time_s"] is not None]
    return {
        "runs": len(sel),
        "ok": len(ok),
        "cameras": len(cams),
        "worst_rotation_deg": max(rot) if rot else None,
        "worst_translation_mm": max(trans) if trans else None,
        "median_rotation_deg": float(np.median(rot)) if rot else None,
        "median_translation_mm": float(np.median(trans)) if trans else None,
        "normalised_rms_translation": _rms(ratio_t),
        "normalised_rms_rotation": _rms(ratio_r),
        "nees_rms": float(np.sqrt(np.mean(nees))) if nees else None,
        "median_time_s": float(np.median(times)) if times else None,
        "failures": [f"seed {r['seed']}: {r['message']}" for r in sel if r["status"] != "ok"],
        "rms_px": [r["rms_px"] for r in sel if r["rms_px"] is not None],
    }


def _f(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _px(x: float) -> str:
    return f"{x:.0f}" if x < 1e5 else f"{x:.1e}"


def peer_margin(runs: list[dict[str, Any]], layout: str) -> dict[str, Any]:
    """How many times smaller ours' worst-camera error is than the best peer's (thesis,
    OpenCV), in translation and rotation. Each peer is compared on the seeds where it
    succeeded, against ours on those same seeds (a peer that leaves a camera uncalibrated on
    one seed is still measured on the others); the best peer is the one closest to ours.
    ``None`` when ours has no result, ``inf`` when every peer failed on every seed."""
    out: dict[str, Any] = {"translation": None, "rotation": None}
    if not summarise(runs, layout, OURS)["ok"]:
        return out
    ratios: dict[str, list[float]] = {"translation": [], "rotation": []}
    for peer in (m.key for m in METHODS if m.kind != "ours"):
        seeds = {
            r["seed"]
            for r in runs
            if r["layout"] == layout and r["method"] == peer and r["status"] == "ok"
        }
        sub = [r for r in runs if r["layout"] == layout and r["seed"] in seeds]
        o, s = summarise(sub, layout, peer), summarise(sub, layout, OURS)
        if not seeds or not s["ok"]:
            continue
        for key, field in (
            ("translation", "worst_translation_mm"),
            ("rotation", "worst_rotation_deg"),
        ):
            ratios[key].append(o[field] / s[field] if s[field] > 0 else math.inf)
    for key, values in ratios.items():
        out[key] = min(values, default=math.inf)
    return out


def acceptance(runs: list[dict[str, Any]], layouts: list[str]) -> dict[str, Any]:
    """Issue 3's acceptance items for ``OURS``: bounds per layout, normalised-error RMS over
    all layouts, and ours being more accurate (worst and median) than every peer method
    (thesis, OpenCV) that did not fail, with a worst-camera error ``PEER_MARGIN`` times
    lower than the best of them, on every layout."""
    out: dict[str, Any] = {"layouts": {}, "passed": True}
    for layout in layouts:
        s = summarise(runs, layout, OURS)
        max_deg, max_mm = BOUNDS[layout]
        ok = (
            s["runs"] > 0
            and s["ok"] == s["runs"]
            and s["worst_rotation_deg"] is not None
            and s["worst_rotation_deg"] <= max_deg
            and s["worst_translation_mm"] <= max_mm
        )
        others = [summarise(runs, layout, m.key) for m in METHODS if m.kind != "ours"]
        best = (
            all(
                o["ok"] == 0
                or o["ok"] < o["runs"]
                or (
                    o["worst_translation_mm"] >= s["worst_translation_mm"]
                    and o["worst_rotation_deg"] >= s["worst_rotation_deg"]
                    and o["median_translation_mm"] >= s["median_translation_mm"]
                    and o["median_rotation_deg"] >= s["median_rotation_deg"]
                )
                for o in others
            )
            if s["ok"]
            else False
        )
        margin = peer_margin(runs, layout)
        margin_ok = all(m is not None and m >= PEER_MARGIN for m in margin.values())
        out["layouts"][layout] = {
            "within_bounds": ok,
            "most_accurate": best,
            "margin": margin,
            "margin_ok": margin_ok,
        }
        out["passed"] &= ok and best and margin_ok
    total = summarise(runs, None, OURS)
    lo, hi = NORMALISED_RMS_RANGE
    out["normalised_rms_translation"] = total["normalised_rms_translation"]
    out["normalised_rms_rotation"] = total["normalised_rms_rotation"]
    out["nees_rms"] = total["nees_rms"]
    honest = (
        total["normalised_rms_translation"] is not None
        and lo <= total["normalised_rms_translation"] <= hi
    )
    out["honest_uncertainty"] = honest
    out["passed"] &= honest
    return out


def _margin(x: float | None) -> str:
    if x is None:
        return "-"
    return "all peers failed" if math.isinf(x) else f"{x:.0f}x"


def _images(payload: dict[str, Any], prefix: str) -> list[str]:
    return [
        f"![{Path(img).stem}]({img})"
        for img in payload.get("images", [])
        if Path(img).stem.startswith(prefix)
    ]


def markdown(payload: dict[str, Any]) -> str:
    runs, meta = payload["runs"], payload["meta"]
    layouts = [lay for lay in meta["layouts"] if any(r["layout"] == lay for r in runs)]
    methods = [m for m in meta["methods"] if any(r["method"] == m for r in runs)]
    by_res: dict[str, list[str]] = {}
    for lay in layouts:
        by_res.setdefault(RESOLUTION.get(lay, "?"), []).append(lay)
    resolutions = "; ".join(f"{' and '.join(lays)} at {res}" for res, lays in by_res.items())
    lines = [
        f"Generated by `{meta['command']}` on {meta['machine']} ({meta['date']}).",
        "",
    ]
    if layouts:
        lines += [
            f"Data: synth defaults (blur 0.6 px, colour noise 2 DN, board {meta['board']}), "
            f"{meta['frames']} frames, seeds {', '.join(map(str, meta['seeds']))}; "
            f"{resolutions}. Errors over the non-reference cameras of every "
            "seed (rotation: angle of `R_est R_true^T`; translation: distance of the camera "
            "centres); worst and median over seeds x cameras. `t/σt`, `r/σr`: RMS of error / "
            "claimed 1-sigma (worst axis); `NEES`: RMS of sqrt(xi^T C^-1 xi / 6) with the full "
            "covariance (1 = honest). Time: median solve time per run (detection excluded; it "
            "is cached and shared), 2-core machine.",
            "",
        ]
    for layout in layouts:
        max_deg, max_mm = BOUNDS[layout]
        n_cams = max(
            (len(r["cameras"]) + len(r["missing"]) for r in runs if r["layout"] == layout),
            default=0,
        )
        lines += [
            f"### {layout} ({n_cams + 1} cameras; bound {max_deg} deg / {max_mm} mm "
            "on every camera)",
            "",
            "| method | runs ok | worst rot (deg) | worst trans (mm) | median rot (deg) "
            "| median trans (mm) | t/σt | r/σr | NEES | time (s) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        notes = []
        for key in methods:
            s = summarise(runs, layout, key)
            label = METHOD_BY_KEY[key].label if key in METHOD_BY_KEY else key
            if key == OURS:
                label = f"**{label}**"
            if s["ok"] == 0:
                rms = [x for x in s["rms_px"] if x is not None]
                rms_txt = ""
                if rms:
                    lo, hi = _px(min(rms)), _px(max(rms))
                    rms_txt = f", OpenCV RMS {lo if lo == hi else f'{lo}-{hi}'} px"
                lines.append(f"| {label} | 0/{s['runs']} | failed{rms_txt} | | | | | | | |")
            else:
                lines.append(
                    f"| {label} | {s['ok']}/{s['runs']} | {_f(s['worst_rotation_deg'], 4)} | "
                    f"{_f(s['worst_translation_mm'])} | {_f(s['median_rotation_deg'], 4)} | "
                    f"{_f(s['median_translation_mm'])} | {_f(s['normalised_rms_translation'], 2)}"
                    f" | {_f(s['normalised_rms_rotation'], 2)} | {_f(s['nees_rms'], 2)} | "
                    f"{_f(s['median_time_s'], 2)} |"
                )
            notes += [f"- {key}, {f}" for f in s["failures"]]
        lines.append("")
        if notes:
            lines += ["Failures:", "", *notes, ""]
    if layouts:
        acc = acceptance(runs, layouts)
        lines += [
            "### Acceptance (issue 3), ours = bundle adjustment with edge corners",
            "",
            "| layout | bound (deg / mm) | worst (deg / mm) | median (deg / mm) | within "
            "bound | beats every peer | best peer's worst / ours' (trans, rot; "
            f"≥ {PEER_MARGIN:g}x) |",
            "|---|---|---|---|---|---|---|",
        ]
        for layout in layouts:
            s = summarise(runs, layout, OURS)
            a = acc["layouts"][layout]
            m = a["margin"]
            lines.append(
                f"| {layout} | {BOUNDS[layout][0]} / {BOUNDS[layout][1]} | "
                f"{_f(s['worst_rotation_deg'], 4)} / {_f(s['worst_translation_mm'])} | "
                f"{_f(s['median_rotation_deg'], 4)} / {_f(s['median_translation_mm'])} | "
                f"{'yes' if a['within_bounds'] else 'NO'} | "
                f"{'yes' if a['most_accurate'] else 'NO'} | "
                f"{_margin(m['translation'])}, {_margin(m['rotation'])}"
                f"{'' if a['margin_ok'] else ' (NO)'} |"
            )
        lo, hi = NORMALISED_RMS_RANGE
        lines += [
            "",
            f"Normalised error RMS over all layouts, seeds and cameras (ours): translation "
            f"{_f(acc['normalised_rms_translation'], 2)}, rotation "
            f"{_f(acc['normalised_rms_rotation'], 2)} (required {lo}-{hi} for translation); "
            f"NEES {_f(acc['nees_rms'], 2)}. "
            f"Overall: {'PASS' if acc['passed'] else 'FAIL'}.",
            "",
            *_images(payload, "accuracy_"),
            *_images(payload, "normalised_error"),
            "",
        ]
    for key, sweep in payload.get("sweeps", {}).items():
        lines += sweep_markdown(key, sweep, meta)
        lines += [*_images(payload, f"sweep_{key}"), ""]
    return "\n".join(lines).rstrip() + "\n"


def _level(sweep: dict[str, Any], value: float) -> str:
    unit = SWEEPS[sweep["key"]].unit if sweep.get("key") in SWEEPS else ""
    return f"{value:g}{unit}"


def sweep_markdown(key: str, sweep: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    """Tables of one sweep: worst / median translation and worst rotation (t/σt) per method
    and level, over seeds x cameras, and the failures, one line per method."""
    runs, levels = sweep["runs"], sweep["levels"]
    methods = [m for m in meta["methods"] if any(r["method"] == m for r in runs)]
    seeds = sorted({r["seed"] for r in runs})
    frames = "" if key == "frames" else f", {sweep['frames']} frames"
    head = "| method | " + " | ".join(_level(sweep, v) for v in levels) + " |"
    rule = "|---|" + "---|" * len(levels)
    lines = [
        f"### Sweep: {sweep['title']} ({sweep['layout']}{frames}, "
        f"seeds {', '.join(map(str, seeds))})",
        "",
        "Everything else at the synth defaults (blur 0.6 px, colour noise 2 DN, no depth bias); "
        "every level is its own rendered set. Worst / median translation error (mm) over "
        "seeds x cameras; `(k/n)`: only k of the n runs succeeded.",
        "",
        head,
        rule,
    ]
    table_r = [head.replace("| method |", "| method, worst rot (deg) (t/σt) |", 1), rule]
    notes = []
    for m in methods:
        cells_t, cells_r = [], []
        sel = [r for r in runs if r["method"] == m]
        for v in levels:
            s = summarise([r for r in sel if r["value"] == v], None, m)
            if s["runs"] == 0:
                cells_t.append("")
                cells_r.append("")
                continue
            if s["ok"] == 0:
                cells_t.append("failed")
                cells_r.append("failed")
                continue
            part = "" if s["ok"] == s["runs"] else f" ({s['ok']}/{s['runs']})"
            cells_t.append(
                f"{s['worst_translation_mm']:.3g} / {s['median_translation_mm']:.3g}{part}"
            )
            ratio = s["normalised_rms_translation"]
            cells_r.append(
                f"{s['worst_rotation_deg']:.3g}" + (f" ({ratio:.2f})" if ratio else "") + part
            )
        label = f"**{m}**" if m == OURS else m
        lines.append(f"| {label} | " + " | ".join(cells_t) + " |")
        table_r.append(f"| {label} | " + " | ".join(cells_r) + " |")
        failed = [r for r in sel if r["status"] != "ok"]
        if failed and len(failed) == len(sel):
            notes.append(f"- {m}: failed in all {len(sel)} runs (e.g. {failed[0]['message']})")
        else:
            notes += [
                f"- {m}, {_level(sweep, r['value'])}, seed {r['seed']}: {r['message']}"
                for r in failed
            ]
    lines += ["", *table_r, ""]
    depth = [r for r in runs if r.get("depth") and r["status"] == "ok"]
    if key == "depth-bias" and depth:
        cells = []
        for v in levels:
            errs = [
                abs(sc["factor"] - sc["true"])
                for r in depth
                if r["value"] == v
                for sc in r["depth"]["scales"].values()
                if sc.get("true") is not None
            ]
            cells.append(f"{max(errs):.2g}" if errs else "-")
        lines += [
            "Only the depth method sees the bias; the board-only methods vary with the "
            "intrinsics, which synth draws after the biases (a biased set has the same poses but "
            "slightly different, exactly known intrinsics).",
            "",
            "Depth stage (bundle-edges-depth): worst |estimated - true depth-scale factor| over "
            "cameras and seeds: "
            + ", ".join(f"{_level(sweep, v)}: {c}" for v, c in zip(levels, cells))
            + ".",
            "",
        ]
    if notes:
        lines += ["Failures:", "", *notes, ""]
    return lines


def write_markdown(path: Path, body: str, command: str) -> None:
    """Replace the generated block of ``path`` (between the begin/end markers) with ``body``,
    keeping any hand-written text around it; a new file gets a title and the command."""
    block = f"{MD_BEGIN}\n{body}{MD_END}\n"
    if path.is_file() and MD_BEGIN in (text := path.read_text()) and MD_END in text:
        head, rest = text.split(MD_BEGIN, 1)
        tail = rest.split(MD_END, 1)[1].lstrip("\n")
        path.write_text(head + block + ("\n" + tail if tail else ""))
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# Accuracy\n\nReproduce: `{command}`\n\n{block}")


# ----------------------------------------------------------------------------- plots
def _only_uncalibrated(run: dict[str, Any]) -> bool:
    """A failed run whose only problem is a camera left uncalibrated (not diverged, not
    raised): the cameras it did calibrate are still worth showing."""
    return bool(run["missing"] and run["cameras"] and "diverged" not in run["message"])


def plot(payload: dict[str, Any], img_dir: Path, rel_to: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs, meta = payload["runs"], payload["meta"]
    img_dir.mkdir(parents=True, exist_ok=True)
    out = []
    methods = [m for m in meta["methods"] if any(r["method"] == m for r in runs)]
    colours = plt.get_cmap("tab10")
    for layout in meta["layouts"]:
        sel = [r for r in runs if r["layout"] == layout]
        if not sel:
            continue
        labels = sorted({(r["seed"], c["camera"]) for r in sel for c in r["cameras"]})
        if not labels:
            continue
        x_of = {lab: i for i, lab in enumerate(labels)}
        fig, axes = plt.subplots(2, 1, figsize=(max(8, 0.35 * len(labels) + 3), 7), sharex=True)
        for k, key in enumerate(methods):
            # ok runs filled; runs that failed only for an uncalibrated camera hollow (the
            # cameras they did calibrate are still compared); diverged runs left out
            for hollow in (False, True):
                shown = [
                    r
                    for r in sel
                    if r["method"] == key
                    and (
                        r["status"] == "ok"
                        if not hollow
                        else r["status"] != "ok" and _only_uncalibrated(r)
                    )
                ]
                xs, rot, trans = [], [], []
                for r in shown:
                    for c in r["cameras"]:
                        xs.append(
                            x_of[(r["seed"], c["camera"])]
                            + (k - (len(methods) - 1) / 2) * 0.7 / len(methods)
                        )
                        rot.append(max(c["rotation_deg"], 1e-5))
                        trans.append(max(c["translation_mm"], 1e-4))
                if not xs:
                    continue
                colour = COLOUR.get(key, colours(k % 10))
                style = dict(
                    label=f"{key} (incomplete run)" if hollow else key,
                    s=28 if key == OURS else 16,
                    marker="o" if key.startswith(("bundle", "posegraph")) else "^",
                    facecolors="none" if hollow else colour,
                    edgecolors=colour,
                )
                axes[0].scatter(xs, rot, **style)
                axes[1].scatter(xs, trans, **style)
        max_deg, max_mm = BOUNDS[layout]
        axes[0].axhline(max_deg, color="k", ls="--", lw=1, label="bound")
        axes[1].axhline(max_mm, color="k", ls="--", lw=1)
        axes[0].set_yscale("log")
        axes[1].set_yscale("log")
        axes[0].set_ylabel("rotation error (deg)")
        axes[1].set_ylabel("translation error (mm)")
        axes[1].set_xticks(range(len(labels)))
        axes[1].set_xticklabels([f"s{s}/{c}" for s, c in labels], rotation=90, fontsize=7)
        axes[0].set_title(
            f"{layout}: error per camera (seed/camera)\nhollow: run with an uncalibrated "
            "camera; diverged runs not shown",
            fontsize=10,
        )
        axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.tight_layout()
        path = img_dir / f"accuracy_{layout}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)

    if runs:
        out.append(plot_normalised(plt, runs, img_dir))
    for key, sweep in payload.get("sweeps", {}).items():
        out.append(plot_sweep(plt, key, sweep, meta, img_dir))
    return [os.path.relpath(p, rel_to) for p in out]


def plot_normalised(plt: Any, runs: list[dict[str, Any]], img_dir: Path) -> Path:
    """Histograms of error / claimed sigma of ours over all layouts, seeds and cameras."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for key, colour in (
        ("bundle-edges", COLOUR["bundle-edges"]),
        ("posegraph-edges", COLOUR["posegraph-edges"]),
        ("bundle-edges-depth", COLOUR["bundle-edges-depth"]),
    ):
        cams = [c for r in runs if r["method"] == key and r["status"] == "ok" for c in r["cameras"]]
        rt = [
            c["translation_mm"] / c["sigma_translation_mm"]
            for c in cams
            if c["sigma_translation_mm"]
        ]
        rr = [c["rotation_deg"] / c["sigma_rotation_deg"] for c in cams if c["sigma_rotation_deg"]]
        bins = np.linspace(0, 5, 26)
        for ax, vals in ((axes[0], rt), (axes[1], rr)):
            if vals:
                ax.hist(
                    np.clip(vals, 0, 5),
                    bins=bins,
                    alpha=0.5,
                    color=colour,
                    label=f"{key} (RMS {_rms(vals):.2f}, n={len(vals)})",
                )
    axes[0].set_xlabel("translation error / sigma_translation_mm")
    axes[1].set_xlabel("rotation error / sigma_rotation_deg")
    for ax in axes:
        ax.axvline(1.0, color="k", ls="--", lw=1)
        ax.set_ylabel("cameras")
        ax.legend(fontsize=8)
    fig.suptitle("Normalised error over all layouts, seeds and cameras (values > 5 in last bin)")
    fig.tight_layout()
    path = img_dir / "normalised_error.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_sweep(plt: Any, key: str, sweep: dict[str, Any], meta: dict[str, Any], img_dir: Path):
    """Worst and median translation (top) and rotation (bottom) error against the swept
    setting, one line per method, log y axis; levels where every run failed are left out."""
    runs, levels = sweep["runs"], sweep["levels"]
    methods = [m for m in meta["methods"] if any(r["method"] == m for r in runs)]
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    panels = (
        (axes[0, 0], "worst_translation_mm", "worst translation error (mm)"),
        (axes[0, 1], "median_translation_mm", "median translation error (mm)"),
        (axes[1, 0], "worst_rotation_deg", "worst rotation error (deg)"),
        (axes[1, 1], "median_rotation_deg", "median rotation error (deg)"),
    )
    for k, m in enumerate(methods):
        sel = [r for r in runs if r["method"] == m]
        stats = [(v, summarise([r for r in sel if r["value"] == v], None, m)) for v in levels]
        stats = [(v, st) for v, st in stats if st["ok"]]
        label = m if stats else f"{m} (failed)"
        style = dict(
            color=COLOUR.get(m, colours(k % 10)),
            marker="o" if m.startswith(("bundle", "posegraph")) else "^",
            lw=2.2 if m == OURS else 1.2,
            ms=6 if m == OURS else 4,
            ls="--" if m.endswith("-depth") else "-",
        )
        for ax, field, _ in panels:
            xs = [v for v, _ in stats]
            ys = [max(st[field], 1e-5) for _, st in stats]
            ax.plot(xs, ys, label=label, **style)
    for ax, _, ylabel in panels:
        ax.set_yscale("log")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
    if key == "frames":
        for ax in axes[1]:
            ax.set_xscale("log", base=2)
            ax.tick_params(axis="x", which="minor", labelbottom=False)
    for ax in axes[1]:
        ax.set_xticks(levels)
        ax.set_xticklabels([f"{v:g}" for v in levels])
        ax.set_xlabel(sweep["title"])
    seeds = sorted({r["seed"] for r in runs})
    frames = "" if key == "frames" else f", {sweep['frames']} frames"
    fig.suptitle(
        f"{sweep['layout']}: error vs {sweep['title']} (seeds {', '.join(map(str, seeds))}"
        f"{frames}; over seeds x cameras)"
    )
    axes[0, 1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    path = img_dir / f"sweep_{key}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- CLI
def _rounded(obj: Any) -> Any:
    """``obj`` with floats cut to 6 significant digits (a smaller, diff-friendly JSON)."""
    if isinstance(obj, float):
        return float(f"{obj:.6g}") if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_rounded(v) for v in obj]
    return obj


def _machine() -> str:
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
        f", {platform.system()}"
    )


_RAN: set[tuple[str, str]] = set()  # (set, method) run by this process


def run_set(
    spec: DatasetSpec,
    methods: list[str],
    board: Board,
    args: argparse.Namespace,
    extra: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """Every method on one set (rendered when missing), a record each, with the set's fields
    (and ``extra``, e.g. the sweep value) added."""
    path = ensure_dataset(args.data, spec, board, args.workers)
    out = []
    for key in methods:
        t0 = time.perf_counter()
        # --rerun: once per set and method (a set can be in the grid and in a sweep)
        rerun = args.rerun and (spec.name, key) not in _RAN
        _RAN.add((spec.name, key))
        rec, cached = cached_run(
            METHOD_BY_KEY[key], path, board, args.data / "cache", args.workers, rerun
        )
        rec = {**rec, **spec.fields(), **(extra or {})}
        out.append(rec)
        worst = max((c["translation_mm"] for c in rec["cameras"]), default=None)
        how = "cached" if cached else f"{time.perf_counter() - t0:.1f} s"
        print(
            f"{spec.name:26s} {key:19s} {rec['status']:6s} worst {_f(worst)} mm ({how}) "
            f"{rec['message']}",
            file=sys.stderr,
            flush=True,
        )
    return out


def sweep_specs(key: str, args: argparse.Namespace) -> list[tuple[float, DatasetSpec]]:
    """(level, set) of every point of one sweep, levels outer, seeds inner."""
    levels = {
        "noise": args.noise_levels,
        "frames": args.frame_counts,
        "depth-bias": args.bias_levels,
    }
    out = []
    for v in dict.fromkeys(levels[key]):
        for seed in args.sweep_seeds or args.seeds:
            spec = DatasetSpec(args.sweep_layout, args.frames, seed)
            if key == "frames":
                spec = replace(spec, frames=int(v))
            else:
                spec = replace(spec, **{SWEEPS[key].field: float(v)})
            out.append((v, spec))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--data",
        type=Path,
        default=Path("bench_data"),
        help="folder of the rendered sets, detection and result caches (reused)",
    )
    p.add_argument(
        "--layouts",
        nargs="*",
        default=list(LAYOUTS),
        choices=LAYOUTS,
        help="layouts of the main grid (none: sweeps only)",
    )
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=40, help="frame sets per rendered rig")
    p.add_argument(
        "--methods", nargs="+", default=[m.key for m in METHODS], choices=[m.key for m in METHODS]
    )
    p.add_argument(
        "--sweep",
        nargs="*",
        default=[],
        choices=list(SWEEPS),
        help="settings to sweep on --sweep-layout (each level a rendered set per seed)",
    )
    p.add_argument("--sweep-layout", default="race", choices=LAYOUTS)
    p.add_argument(
        "--sweep-seeds", nargs="+", type=int, default=None, help="seeds of the sweeps (--seeds)"
    )
    p.add_argument(
        "--noise-levels",
        nargs="+",
        type=float,
        default=[0.0, 2.0, 5.0, 10.0],
        help="colour noise sigma (DN) of the noise sweep",
    )
    p.add_argument(
        "--frame-counts",
        nargs="+",
        type=int,
        default=[10, 20, 40, 80],
        help="frame sets of the frames sweep",
    )
    p.add_argument(
        "--bias-levels",
        nargs="+",
        type=float,
        default=[0.0, 0.003, 0.006, 0.01],
        help="max relative depth-scale error per camera of the depth-bias sweep",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="processes for rendering and detection",
    )
    p.add_argument(
        "--rerun", action="store_true", help="run every method again (ignore cached results)"
    )
    p.add_argument(
        "--json", type=Path, default=Path("docs/accuracy.json"), help="raw results (written)"
    )
    p.add_argument(
        "--md",
        type=Path,
        default=None,
        help="markdown file for the tables (its generated block is replaced)",
    )
    p.add_argument("--img", type=Path, default=Path("docs/img"), help="folder for the plots")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument(
        "--from-json",
        type=Path,
        default=None,
        help="re-make tables and plots from this JSON; run nothing",
    )
    args = p.parse_args(argv)
    command = "python tools/bench_accuracy.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )

    if args.from_json:
        payload = json.loads(args.from_json.read_text())
    else:
        board = thesis_board()
        args.data.mkdir(parents=True, exist_ok=True)
        runs = []
        for layout in args.layouts:
            for seed in args.seeds:
                runs += run_set(DatasetSpec(layout, args.frames, seed), args.methods, board, args)
        sweeps = {}
        for key in dict.fromkeys(args.sweep):  # in the given order, once each
            sweep_runs = []
            for v, spec in sweep_specs(key, args):
                sweep_runs += run_set(spec, args.methods, board, args, {"value": v})
            sweeps[key] = {
                "key": key,
                "title": SWEEPS[key].title,
                "field": SWEEPS[key].field,
                "layout": args.sweep_layout,
                "frames": args.frames,
                "levels": sorted({v for v, _ in sweep_specs(key, args)}),
                "runs": sweep_runs,
            }
        import cv2
        import gtsam

        payload = {
            "meta": {
                "command": command,
                "machine": _machine(),
                "layouts": args.layouts,
                "seeds": args.seeds,
                "sweep_seeds": args.sweep_seeds or args.seeds,
                "frames": args.frames,
                "methods": args.methods,
                "board": board.name,
                "date": time.strftime("%Y-%m-%d"),
                "opencv": cv2.__version__,
                "gtsam": getattr(gtsam, "__version__", "?"),
                "bounds": BOUNDS,
                "synth_defaults": {
                    k: (list(v) if isinstance(v, tuple) else v)
                    for k, v in SYNTH_DEFAULTS.__dict__.items()
                },
                "code": code_hash(),
            },
            "runs": runs,
            "sweeps": sweeps,
        }
    layouts = [lay for lay in payload["meta"]["layouts"]]
    payload["acceptance"] = acceptance(payload["runs"], layouts)
    md_dir = args.md.parent if args.md else Path.cwd()
    if not args.no_plots:
        payload["images"] = plot(payload, args.img, md_dir)
    if not args.from_json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(_rounded(payload), indent=1, default=float))
    body = markdown(payload)
    print(body)
    if args.md:
        write_markdown(args.md, body, payload["meta"]["command"])
    # sweeps only (no layout): nothing to accept
    return 0 if not layouts or payload["acceptance"]["passed"] else 1


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
