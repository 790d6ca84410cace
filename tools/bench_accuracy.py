"""Accuracy benchmark on synthetic rigs with ground truth: ours against the peers.

    python tools/bench_accuracy.py --data bench_data --seeds 0 1 2 --md docs/accuracy.md

Renders every layout x seed once with the synth defaults (cached under ``--data``; an existing
render is reused), runs every method on the same images and compares each camera's
``T_ref_cam`` with ``ground_truth.yaml``. Writes the raw results (``--json``), the markdown
tables (stdout and ``--md``) and plots (``--img``). ``--from-json`` re-makes the tables and
plots from a saved JSON without running anything.

Methods (same images, intrinsics fixed to the rig's):

- ``thesis``: the seed thesis's pipeline (tools/peers.py): OpenCV's unrefined corners, per-view
  PnP, pose graph with one isotropic edge noise, plain least squares.
- ``opencv-*``: ``cv2.calibrateMultiview`` (OpenCV 5) on our SUBPIX or edge-fit detections.
- ``posegraph-*``: ours, ``CalibrationConfig(method="posegraph")`` (PnP-covariance weighted,
  robust), with ``DetectionConfig(refinement="subpix")`` or ``"edges"``.
- ``bundle-*``: ours, joint bundle adjustment on the corners (the default), same two corners;
  board only (``refine="none"``: the depth stage is left out).

Errors are over the non-reference cameras (the reference is the gauge: exact by definition).
The uncertainty check divides each camera's error by the sigma the method claims for it
(``sigma_translation_mm`` / ``sigma_rotation_deg``, 1-sigma along the worst axis) and takes the
RMS over seeds and cameras; honest sigmas give 0.5-2 (1 for an error along the worst axis,
sqrt(3) for an isotropic one). ``NEES`` is the stricter check with the full 6x6 covariance:
RMS of sqrt(xi^T C^-1 xi / 6), ``T_true = T_est Exp(xi)``, 1 when the covariance is right.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/peers.py

from peers import opencv_multiview, thesis_method  # noqa: E402

from rgbd_calib.board import Board, thesis_board  # noqa: E402
from rgbd_calib.calibrate import CalibrationConfig, calibrate, detect_dataset  # noqa: E402
from rgbd_calib.dataset import FolderDataset  # noqa: E402
from rgbd_calib.detection import DetectionConfig  # noqa: E402
from rgbd_calib.geometry import matrix_to_rotvec, transform_error  # noqa: E402
from rgbd_calib.synth import SynthParams, load_ground_truth, synthesize  # noqa: E402

LAYOUTS = ("race", "ring", "thesis-line")
# Acceptance bounds of issue 3 (every camera): rotation (deg), translation (mm).
BOUNDS = {"race": (0.1, 1.0), "ring": (0.05, 0.5), "thesis-line": (0.05, 0.5)}
NORMALISED_RMS_RANGE = (0.5, 2.0)
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
)
METHOD_BY_KEY = {m.key: m for m in METHODS}


# ----------------------------------------------------------------------------- data
def dataset_name(layout: str, frames: int, seed: int) -> str:
    return f"{layout}-f{frames}-s{seed}"


def ensure_dataset(
    data: Path, layout: str, frames: int, seed: int, board: Board, workers: int
) -> Path:
    """The rendered set (synth defaults), rendering it when ``ground_truth.yaml`` is missing."""
    path = data / dataset_name(layout, frames, seed)
    if (path / "ground_truth.yaml").is_file():
        return path
    print(f"rendering {path} ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    synthesize(path, layout, frames, seed, board, SynthParams(), workers=workers)
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
) -> tuple[dict[str, Any], dict[str, str], float]:
    # refine="none": the board-only calibration this benchmark is about (the default "auto"
    # adds the depth stage, colored ICP, on sets with depth)
    config = CalibrationConfig(
        detection=DetectionConfig(refinement=method.refinement),
        method=method.final,
        workers=workers,
        refine="none",
    )
    result = calibrate(dataset, board, config, cache_dir=cache)
    solve_s = sum(v for k, v in result.timings_s.items() if k != "detection")
    return dict(result.extrinsics.cameras), dict(result.extrinsics.unconnected), solve_s


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
                cams, missing, rec["time_s"] = _run_ours(method, dataset, board, cache, workers)
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


def acceptance(runs: list[dict[str, Any]], layouts: list[str]) -> dict[str, Any]:
    """Issue 3's acceptance items for ``OURS``: bounds per layout, normalised-error RMS over
    all layouts, and ours being more accurate (worst and median) than every peer method
    (thesis, OpenCV) that did not fail, on every layout."""
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
        out["layouts"][layout] = {"within_bounds": ok, "most_accurate": best}
        out["passed"] &= ok and best
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


def markdown(payload: dict[str, Any]) -> str:
    runs, meta = payload["runs"], payload["meta"]
    layouts = [lay for lay in meta["layouts"] if any(r["layout"] == lay for r in runs)]
    methods = [m for m in meta["methods"] if any(r["method"] == m for r in runs)]
    lines = [
        f"Generated by `{meta['command']}` on {meta['machine']} ({meta['date']}).",
        "",
        f"Data: synth defaults (blur 0.6 px, colour noise 2 DN, board {meta['board']}), "
        f"{meta['frames']} frames, seeds {', '.join(map(str, meta['seeds']))}; race at 848x480, "
        "ring and thesis-line at 1280x720. Errors over the non-reference cameras of every "
        "seed (rotation: angle of `R_est R_true^T`; translation: distance of the camera "
        "centres); worst and median over seeds x cameras. `t/σt`, `r/σr`: RMS of error / "
        "claimed 1-sigma (worst axis); `NEES`: RMS of sqrt(xi^T C^-1 xi / 6) with the full "
        "covariance (1 = honest). Time: median solve time per run (detection excluded; it is "
        "cached and shared), 2-core machine.",
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
                rms_txt = f", OpenCV RMS {_px(min(rms))}-{_px(max(rms))} px" if rms else ""
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
    acc = payload.get("acceptance") or acceptance(runs, layouts)
    lines += [
        "### Acceptance (issue 3), ours = bundle adjustment with edge corners",
        "",
        "| layout | bound (deg / mm) | worst (deg / mm) | median (deg / mm) | within "
        "bound | beats every peer |",
        "|---|---|---|---|---|---|",
    ]
    for layout in layouts:
        s = summarise(runs, layout, OURS)
        a = acc["layouts"][layout]
        lines.append(
            f"| {layout} | {BOUNDS[layout][0]} / {BOUNDS[layout][1]} | "
            f"{_f(s['worst_rotation_deg'], 4)} / {_f(s['worst_translation_mm'])} | "
            f"{_f(s['median_rotation_deg'], 4)} / {_f(s['median_translation_mm'])} | "
            f"{'yes' if a['within_bounds'] else 'NO'} | {'yes' if a['most_accurate'] else 'NO'} |"
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
    ]
    for img in payload.get("images", []):
        lines.append(f"![{Path(img).stem}]({img})")
    return "\n".join(lines).rstrip() + "\n"


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
            ok = [r for r in sel if r["method"] == key and r["status"] == "ok"]
            xs, rot, trans = [], [], []
            for r in ok:
                for c in r["cameras"]:
                    xs.append(
                        x_of[(r["seed"], c["camera"])]
                        + (k - (len(methods) - 1) / 2) * 0.7 / len(methods)
                    )
                    rot.append(max(c["rotation_deg"], 1e-5))
                    trans.append(max(c["translation_mm"], 1e-4))
            if not xs:
                continue
            style = dict(
                color=colours(k),
                label=key,
                s=28 if key == OURS else 16,
                marker="o" if key.startswith(("bundle", "posegraph")) else "^",
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
        axes[0].set_title(f"{layout}: error per camera (seed/camera; failed runs not shown)")
        axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.tight_layout()
        path = img_dir / f"accuracy_{layout}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for key, colour in (("bundle-edges", colours(0)), ("posegraph-edges", colours(1))):
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
    out.append(path)
    return [os.path.relpath(p, rel_to) for p in out]


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--data",
        type=Path,
        default=Path("bench_data"),
        help="folder of the rendered sets and detection caches (reused)",
    )
    p.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=LAYOUTS)
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=40, help="frame sets per rendered rig")
    p.add_argument(
        "--methods", nargs="+", default=[m.key for m in METHODS], choices=[m.key for m in METHODS]
    )
    p.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="processes for rendering and detection",
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
                path = ensure_dataset(args.data, layout, args.frames, seed, board, args.workers)
                for key in args.methods:
                    t0 = time.perf_counter()
                    rec = run_method(
                        METHOD_BY_KEY[key], path, board, args.data / "cache", args.workers
                    )
                    rec.update(layout=layout, seed=seed, frames=args.frames, dataset=path.name)
                    runs.append(rec)
                    worst = max((c["translation_mm"] for c in rec["cameras"]), default=None)
                    print(
                        f"{layout:12s} seed {seed} {key:17s} {rec['status']:6s} worst "
                        f"{_f(worst)} mm ({time.perf_counter() - t0:.1f} s) {rec['message']}",
                        file=sys.stderr,
                        flush=True,
                    )
        import cv2
        import gtsam

        payload = {
            "meta": {
                "command": command,
                "machine": _machine(),
                "layouts": args.layouts,
                "seeds": args.seeds,
                "frames": args.frames,
                "methods": args.methods,
                "board": board.name,
                "date": time.strftime("%Y-%m-%d"),
                "opencv": cv2.__version__,
                "gtsam": getattr(gtsam, "__version__", "?"),
                "bounds": BOUNDS,
            },
            "runs": runs,
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
    return 0 if payload["acceptance"]["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
