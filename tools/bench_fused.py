"""The fused cloud against the true scene surfaces, per camera (issue 33, item 5).

    python tools/bench_fused.py WORKDIR [--layouts race ring race16] [--frames N] [--seed S]

Per layout the rig is rendered twice with the same seed (``rgbd-calib synth``): ``errors``,
each camera's depth off by the issue's depth errors (:data:`DEPTH_ERRORS`: a disparity offset
within +-0.2 px, its gradients and curvature within +-0.05 px, a scale within +-0.5 %, the
depth-to-colour pose within 0.2 deg / 1 mm per axis), and ``true`` (no depth error). Each is
calibrated with ``rgbd-calib calibrate``, default settings (``--refine none`` would skip the
depth stage and write no ``fused.ply``): ``errors`` twice, with
the depth model (``depth.model: auto``, the default) and without it (``depth.model: none``: the
depth-scale factor alone, as before the model), ``true`` once. Renders and calibrations found in
WORKDIR are reused.

Each camera's points are read from ``fused.ply`` (its ``camera`` property), mapped into the
world with the TRUE reference pose (so the error of the estimated extrinsics counts), and
measured against the scene's rectangles (:func:`rgbd_calib.synth.surfaces.surface_distances`:
signed along the surface normal, positive beyond the surface as the camera sees it, points
farther than 5 cm from every surface left out). Variants:

- ``model``: the errors render with its depth model (what ``fused.ply`` is now);
- ``scale``: the errors render calibrated with ``depth.model: none`` (its own ``fused.ply``);
- ``raw``: the ``model`` cloud with the fitted model undone point by point (the camera's own
  depth, identity model: same pixels, same extrinsics);
- ``true``: the true-depth render with its own calibration (the reference).

Reported per camera: the median signed distance (mm, all matched points), the 90th percentile
of |distance| for points within 2 m of the camera (mm; ``--near-m``), the point counts, the
median per distance band; per camera the fitted model against the truth (``ground_truth.yaml``
``depth_model``) in sigmas; and the clean-rig check: how far the model fitted on the true-depth
render moves each camera's points (median |shift|, mm; the issue asks for identity models and
no cloud moved by more than 0.3 mm).
A markdown report goes to stdout and WORKDIR/bench_fused.md, the numbers to bench_fused.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from dataclasses import fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from toolmain import ToolError

from rgbd_calib.core.depth_model import PARAMETERS
from rgbd_calib.core.geometry import invert_transform, transform_points
from rgbd_calib.core.ply import read_ply
from rgbd_calib.core.yamlio import read_yaml_mapping
from rgbd_calib.model.calib_folder import load_depth_scales
from rgbd_calib.model.depth_model_file import load_depth_models
from rgbd_calib.model.results import load_extrinsics
from rgbd_calib.synth.ground_truth import load_ground_truth
from rgbd_calib.synth.layouts import make_rig
from rgbd_calib.synth.params import SynthParams
from rgbd_calib.synth.surfaces import MAX_DISTANCE_M, surface_distances

# the depth errors (rgbd-calib synth options; docs/synthetic.md, "Depth errors")
DEPTH_ERRORS = ["--depth-bias", "0.005", "--depth-disparity-offset", "0.2",
                "--depth-disparity-field", "0.05", "--depth-pose-error", "0.2", "1"]
NEAR_M = 2.0  # default: p90 of |distance| over points this close to their camera (--near-m)
CLEAN_SHIFT_MM = 0.3  # the issue: on a clean rig no cloud moved by more than this
BANDS_M = (0.0, 1.0, 2.0, 3.0, 4.0)  # distance bands of the per-band bias table
VARIANTS = ("model", "scale", "raw", "true")
FEW_MATCHED = 0.95  # a band with fewer of its points matched is marked in the table


# ----------------------------------------------------------------------------- runs
def _cli(args: list[str], log: Path) -> float:
    """``rgbd-calib ARGS`` with its output in ``log``; wall time (s). Raises on failure."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        done = subprocess.run([sys.executable, "-m", "rgbd_calib.cli", *args], stdout=f,
                              stderr=subprocess.STDOUT)
    if done.returncode != 0:
        raise ToolError(f"rgbd-calib {' '.join(args)} failed (exit {done.returncode}); "
                        f"see {log}")
    return time.perf_counter() - t0


def render(folder: Path, layout: str, frames: int, seed: int, errors: bool,
           times: dict[str, float]) -> None:
    """``rgbd-calib synth`` into ``folder`` unless a render of these settings is there."""
    gt_file = folder / "ground_truth.yaml"
    if gt_file.is_file():
        data = read_yaml_mapping(gt_file, "ground truth")
        same = (data["layout"] == layout and data["seed"] == seed
                and len(data["T_ref_board"]) == frames
                and (data["params"]["depth_bias"] > 0) == errors)
        if not same:
            raise SystemExit(f"{folder} holds another render; remove it or choose another WORKDIR")
        return
    if folder.exists():
        shutil.rmtree(folder)  # an interrupted render
    args = ["synth", str(folder), "--layout", layout, "--frames", str(frames), "--seed",
            str(seed), *(DEPTH_ERRORS if errors else [])]
    times[f"render {folder.name}"] = _cli(args, folder.parent / f"{folder.name}.render.log")


def calibrate(dataset: Path, out: Path, refine: str, depth_model: str,
              times: dict[str, float], cache_from: Path | None = None,
              depth_options: tuple[str, ...] = ()) -> None:
    """``rgbd-calib calibrate`` into ``out`` (``depth.model`` set by a config file) unless
    it holds a finished run; ``cache_from``: another run of the same dataset whose marker
    detections are copied in (the detection does not depend on the depth settings)."""
    if (out / "fused.ply").is_file() and (out / "depth_model.yaml").is_file() == (
            depth_model == "auto"):
        return
    out.mkdir(parents=True, exist_ok=True)
    if cache_from is not None and (cache_from / "cache").is_dir():
        shutil.copytree(cache_from / "cache", out / "cache", dirs_exist_ok=True)
    config = out.parent / f"{out.name}.config.yaml"
    config.write_text(f"depth:\n  model: {depth_model}\n"
                      + "".join(f"  {o.replace('=', ': ', 1)}\n" for o in depth_options))
    args = ["calibrate", str(dataset), "--out", str(out), "--config", str(config),
            *([] if refine == "auto" else ["--refine", refine])]
    times[f"calibrate {out.name}"] = _cli(args, out.parent / f"{out.name}.log")


# ----------------------------------------------------------------------------- truth
def synth_params(raw: dict[str, Any]) -> SynthParams:
    """The :class:`SynthParams` of ``ground_truth.yaml``'s ``params`` (lists as tuples)."""

    def tuples(v):
        return tuple(tuples(x) for x in v) if isinstance(v, list) else v

    names = {f.name for f in fields(SynthParams)}
    return SynthParams(**{k: tuples(v) for k, v in raw.items() if k in names})


def true_rig(render_dir: Path):
    """The render's rig rebuilt from its ground truth (layout, seed, params), checked
    against the ground truth's extrinsics."""
    data = read_yaml_mapping(render_dir / "ground_truth.yaml", "ground truth")
    rig = make_rig(str(data["layout"]), int(data["seed"]), synth_params(data["params"]))
    gt = load_ground_truth(render_dir)
    for cam in rig.cameras:
        if not np.allclose(rig.T_ref_cam(cam), gt.T_ref_cam[cam.name], atol=1e-9):
            raise SystemExit(f"{render_dir}: make_rig does not rebuild {cam.name}'s pose")
    return rig, gt


# ----------------------------------------------------------------------------- clouds
def fused_clouds(calib: Path) -> dict[str, np.ndarray]:
    """camera -> its points ``(N,3)`` of ``fused.ply`` (metres, reference frame)."""
    points, _, index, names = read_ply(calib / "fused.ply")
    return {name: points[index == k] for k, name in enumerate(names)}


def camera_stats(signed_m: np.ndarray, range_m: np.ndarray, near_m: float = NEAR_M,
                 ) -> dict[str, Any]:
    """Median signed distance (mm, every matched point), p90 of |distance| within
    ``near_m`` of the camera (mm), counts, and the median per distance band (mm)."""
    ok = np.isfinite(signed_m)
    near = ok & (range_m <= near_m)
    bands, matched = {}, {}
    for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:]):
        band = (range_m > lo) & (range_m <= hi)
        sel = ok & band
        bands[f"{lo:g}-{hi:g}"] = (float(1e3 * np.median(signed_m[sel]))
                                   if np.count_nonzero(sel) >= 50 else None)
        matched[f"{lo:g}-{hi:g}"] = (np.count_nonzero(sel) / np.count_nonzero(band)
                                     if band.any() else None)
    return {
        "bias_mm": float(1e3 * np.median(signed_m[ok])) if ok.any() else None,
        "p90_near_mm": float(1e3 * np.percentile(np.abs(signed_m[near]), 90))
        if near.any() else None,
        "bias_near_mm": float(1e3 * np.median(signed_m[near])) if near.any() else None,
        "n": int(signed_m.size),
        "n_matched": int(np.count_nonzero(ok)),
        "n_near": int(np.count_nonzero(near)),
        "bands_mm": bands,
        "bands_matched": matched,  # fraction of the band's points within MAX_DISTANCE_M
    }


def measure(calib: Path, render_dir: Path, variants: dict[str, str],
            near_m: float = NEAR_M) -> dict[str, Any]:
    """Per camera of ``calib``'s ``fused.ply``: :func:`camera_stats` of each variant in
    ``variants`` (name -> ``as-is``, ``raw`` (the model undone) or ``scale`` (the model undone,
    divided by the depth-scale factor)), and the median |shift| the model applied (mm)."""
    rig, _ = true_rig(render_dir)
    T_world_ref = rig.cameras[rig.reference_index].T_world_cam
    extrinsics = load_extrinsics(calib / "extrinsics.yaml")
    models = (load_depth_models(calib) if (calib / "depth_model.yaml").is_file() else {})
    factors = load_depth_scales(calib / "report.json")
    eyes = {c.name: c.T_world_cam[:3, 3] for c in rig.cameras}
    out: dict[str, Any] = {}
    for cam, points_ref in fused_clouds(calib).items():
        T_cam_ref = invert_transform(extrinsics.T_ref_cam(cam))
        points_cam = transform_points(T_cam_ref, points_ref)
        model = models.get(cam)
        raw_cam = points_cam if model is None else model.measured_points(points_cam)
        entry: dict[str, Any] = {
            "shift_mm": float(1e3 * np.median(np.linalg.norm(points_cam - raw_cam, axis=1))),
        }
        for name, how in variants.items():
            p_cam = {"as-is": points_cam, "raw": raw_cam,
                     "scale": raw_cam / factors.get(cam, 1.0)}[how]
            p_world = transform_points(T_world_ref @ extrinsics.T_ref_cam(cam), p_cam)
            d = surface_distances(rig.scene, p_world, eyes[cam])
            entry[name] = camera_stats(d.signed_m,
                                       np.linalg.norm(p_world - eyes[cam], axis=1), near_m)
        out[cam] = entry
    return out


def model_vs_truth(calib: Path, render_dir: Path) -> dict[str, list[dict[str, Any]]]:
    """Per camera, per parameter estimated or non-zero in the truth: the estimate, the
    truth, the sigma and the error in sigmas (None where nothing was estimated)."""
    _, gt = true_rig(render_dir)
    models = load_depth_models(calib) if (calib / "depth_model.yaml").is_file() else {}
    out = {}
    for cam, m in models.items():
        truth = gt.depth_model.get(cam)
        rows = []
        for p in PARAMETERS:
            t = truth.value(p) if truth is not None else (1.0 if p == "scale" else 0.0)
            sigma = m.sigmas.get(p)
            if sigma is None and t == (1.0 if p == "scale" else 0.0):
                continue
            rows.append({"parameter": p, "estimate": m.value(p), "truth": t, "sigma": sigma,
                         "z": (m.value(p) - t) / sigma if sigma else None})
        out[cam] = rows
    return {"terms": {c: list(m.terms) for c, m in models.items()}, "parameters": out}


# ----------------------------------------------------------------------------- report
def _f(x, digits=2) -> str:
    return "-" if x is None else f"{x:+.{digits}f}" if digits >= 0 else f"{x:.{-digits}f}"


def _few(fraction: float | None) -> str:
    return "*" if fraction is not None and fraction < FEW_MATCHED else ""


def markdown(layout: str, seed: int, frames: int, res: dict[str, Any],
             near_m: float = NEAR_M) -> str:
    m = res["cameras"]
    lines = [f"### {layout}, seed {seed}, {frames} frame sets", "",
             "| camera | bias mm (errors, model) | bias (errors, scale only) | "
             f"bias (errors, raw) | bias (true depth) | p90<{near_m:g}m (errors, model) | "
             "p90 (scale only) | p90 (raw) | p90 (true depth) | p90 ratio model/true | "
             "points (model / true) |",
             "|---" * 11 + "|"]
    for cam, e in m.items():
        p90 = {v: e[v]["p90_near_mm"] for v in VARIANTS}
        ratio = (p90["model"] / p90["true"] if p90["model"] and p90["true"] else None)
        lines.append(
            f"| {cam} | " + " | ".join(_f(e[v]["bias_mm"]) for v in VARIANTS) + " | "
            + " | ".join(_f(p90[v], -2) for v in VARIANTS) + f" | {_f(ratio, -2)} | "
            f"{e['model']['n_matched']} / {e['true']['n_matched']} |")
    lines += ["", "Median signed distance per distance band from the camera (mm; model / "
              f"scale only / raw / true depth; * fewer than {100 * FEW_MATCHED:g} % of the "
              f"band's points within {1e3 * MAX_DISTANCE_M:g} mm of a surface, the median "
              "understates):", "",
              "| camera | " + " | ".join(f"{b} m" for b in m[next(iter(m))]["model"]
                                        ["bands_mm"]) + " |",
              "|---" * (len(BANDS_M)) + "|"]
    for cam, e in m.items():
        cells = [" / ".join(_f(e[v]["bands_mm"][b], 1) + _few(e[v]["bands_matched"][b])
                            for v in VARIANTS) for b in e["model"]["bands_mm"]]
        lines.append(f"| {cam} | " + " | ".join(cells) + " |")
    lines += ["", "Depth model (errors render) against the truth: estimate (truth) "
              "error/sigma, for the parameters estimated or non-zero in the truth:", ""]
    mt = res["model_vs_truth"]
    for cam, rows in mt["parameters"].items():
        cells = []
        for r in rows:
            z = "not estimated" if r["z"] is None else f"{r['z']:+.1f} sigma"
            cells.append(f"{r['parameter']} {r['estimate']:+.4g} ({r['truth']:+.4g}) {z}")
        lines.append(f"- {cam} [{'+'.join(mt['terms'][cam]) or 'identity'}]: "
                     + "; ".join(cells))
    clean = res["clean"]
    lines += ["", "Clean rig (true-depth render): terms chosen and median |shift| the model "
              f"applied to each camera's points (bound {CLEAN_SHIFT_MM} mm):", "",
              "| camera | terms | median shift mm |", "|---|---|---|"]
    for cam, e in m.items():
        terms = "+".join(clean["terms"].get(cam, [])) or "identity"
        lines.append(f"| {cam} | {terms} | {e['true_shift_mm']:.3f} |")
    return "\n".join(lines) + "\n"


def run_layout(workdir: Path, layout: str, frames: int, seed: int, refine: str,
               times: dict[str, float], near_m: float = NEAR_M,
               depth_options: tuple[str, ...] = ()) -> dict[str, Any]:
    base = workdir / f"{layout}-{seed}-{frames}"
    base.mkdir(parents=True, exist_ok=True)
    errors, true = base / "errors", base / "true"
    render(errors, layout, frames, seed, True, times)
    render(true, layout, frames, seed, False, times)
    with_model, scale_only, clean = (base / "calib-errors-model", base / "calib-errors-nomodel",
                                     base / "calib-true")
    calibrate(errors, with_model, refine, "auto", times, depth_options=depth_options)
    calibrate(errors, scale_only, refine, "none", times, cache_from=with_model)
    calibrate(true, clean, refine, "auto", times, depth_options=depth_options)
    t0 = time.perf_counter()
    a = measure(with_model, errors, {"model": "as-is", "raw": "raw"}, near_m)
    b = measure(scale_only, errors, {"scale": "as-is"}, near_m)
    c = measure(clean, true, {"true": "as-is"}, near_m)
    cameras = {cam: {**a[cam], "scale": b[cam]["scale"], "true": c[cam]["true"],
                     "true_shift_mm": c[cam]["shift_mm"]} for cam in a}
    times[f"measure {base.name}"] = time.perf_counter() - t0
    return {"cameras": cameras, "model_vs_truth": model_vs_truth(with_model, errors),
            "clean": model_vs_truth(clean, true)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--layouts", nargs="+", default=["race"])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--refine", default="auto", help="calibrate --refine (default auto)")
    ap.add_argument("--near-m", type=float, default=NEAR_M,
                    help="p90 over points this close to their camera (m; default 2: the ring's "
                    "cameras see nothing that close, give 3 there)")
    ap.add_argument("--depth-option", action="append", default=[], metavar="KEY=VALUE",
                    help="a depth setting for the model calibrations (repeatable), e.g. "
                    "model_unseen_views=true; give each setting its own WORKDIR")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    report = [f"Run {datetime.now(UTC):%Y-%m-%d %H:%M} UTC: "
              f"`python tools/bench_fused.py {args.workdir} --layouts {' '.join(args.layouts)} "
              f"--frames {args.frames} --seed {args.seed} --refine {args.refine} "
              f"--near-m {args.near_m:g}`; depth errors "
              f"`{' '.join(DEPTH_ERRORS)}`; points farther than {1e3 * MAX_DISTANCE_M:g} mm "
              "from every true surface left out.", ""]
    results = {}
    for layout in args.layouts:
        times: dict[str, float] = {}
        results[layout] = run_layout(args.workdir, layout, args.frames, args.seed,
                                     args.refine, times, args.near_m,
                                     tuple(args.depth_option))
        results[layout]["times_s"] = times
        report.append(markdown(layout, args.seed, args.frames, results[layout], args.near_m))
        report.append("Wall time (s): " + ", ".join(f"{k} {v:.0f}" for k, v in times.items())
                      + "\n")
        print("\n".join(report[-2:]), flush=True)
    (args.workdir / "bench_fused.md").write_text("\n".join(report))
    (args.workdir / "bench_fused.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
