"""Real-rig imperfections benchmark: what a misglued back sheet, lying intrinsics and an
unlisted lens distortion cost each method, and what the self-calibrating model recovers.

    python tools/bench_imperfections.py --data /work/bench13_data --seeds 11 --workers 1 \
        --md /work/bench13_data/imperfections.md

Sets (docs/synthetic.md), each rendered once per layout x seed under ``--data`` (reused when
its ground_truth.yaml exists): ``clean``; ``glue`` (``--glue 1.5 -1.0 0.3``); ``intrinsics``
(``--intrinsics-error 0.7 3``); ``distortion`` (``--distortion 0.08 -0.15 0.0005 -0.0005 0.03
--rig-distortion zeros``); ``all`` (the three at once). An intrinsics error only changes
rig.yaml (the images are byte-identical), so ``intrinsics`` and ``all`` link the images of
``clean`` and ``glue+distortion`` and write their own rig.yaml and ground_truth.yaml.
``--board-volume S`` and ``--closeups N`` render every set with synth's options of that name
(folder suffixes ``-vS``, ``-cN``).

Methods: ``fixed`` (bundle, intrinsics and board file taken as exact), ``auto`` (bundle with
``bundle.intrinsics``/``bundle.board`` auto: the self-calibrating model selection), ``thesis``
(tools/peers.py). All with ``refine="none"``. Each result is cached per set and method under
``--data/cache/<set>/results`` (keyed by the code), so a re-run only computes what is missing.
A failure is recorded with its traceback and the run goes on. ``--from-json`` re-makes the
summaries and tables from a saved JSON without running anything.

Intrinsics columns compare the model a method ended with (refined, or rig.yaml's) against the
truth: focal and centre errors and the worst reprojection difference of the true rays over
the whole image and over the convex hull of that camera's detected corners.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from matplotlib.path import Path as Polygon

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy import _f, _rounded, camera_record, code_hash  # noqa: E402
from peers import thesis_method  # noqa: E402

from rgbd_calib.core.camera import CameraIntrinsics  # noqa: E402
from rgbd_calib.core.config import BundleConfig, CalibrationConfig  # noqa: E402
from rgbd_calib.core.geometry import transform_error  # noqa: E402
from rgbd_calib.core.yamlio import atomic_write_text, read_yaml_mapping, write_yaml  # noqa: E402
from rgbd_calib.model.board import Board, thesis_board  # noqa: E402
from rgbd_calib.model.dataset import FolderDataset  # noqa: E402
from rgbd_calib.model.rig import Rig, parse_camera, save_rig  # noqa: E402
from rgbd_calib.pipelines.calibrate import calibrate  # noqa: E402
from rgbd_calib.synth.render import SynthParams, load_ground_truth, make_rig, synthesize  # noqa: E402

GLUE = {"glue": (1.5, -1.0, 0.3)}
INTR = {"intrinsics_error": (0.7, 3.0)}
DIST = {"distortion": (0.08, -0.15, 0.0005, -0.0005, 0.03), "rig_distortion": "zeros"}
SETS: dict[str, dict[str, Any]] = dict(clean={}, glue=GLUE, intrinsics=INTR, distortion=DIST)
SETS["all"] = {**GLUE, **INTR, **DIST}
IMAGES = {"intrinsics": "clean", "all": "glue+distortion"}  # sets that only change rig.yaml
IMAGE_SETS = {**SETS, "glue+distortion": {**GLUE, **DIST}}
METHODS = ("fixed", "auto", "thesis")
RECORD_VERSION = 4


def set_name(layout: str, frames: int, seed: int, name: str, volume: float = 1.0,
             closeups: int = 0) -> str:
    """A set's folder name (``-vS`` for a board volume other than the layout's, ``-cN`` for
    N close-ups per camera)."""
    return (f"{layout}-f{frames}-s{seed}-{name}" + (f"-v{volume:g}" if volume != 1.0 else "")
            + (f"-c{closeups}" if closeups else ""))


def ensure_set(
    data: Path, layout: str, frames: int, seed: int, name: str, board: Board, workers: int,
    volume: float = 1.0, closeups: int = 0,
) -> Path:
    """The rendered set, rendering (or linking, for an intrinsics error) what is missing;
    ``volume``, ``closeups``: synth's ``--board-volume`` and ``--closeups``."""
    path = data / set_name(layout, frames, seed, name, volume, closeups)
    if (path / "ground_truth.yaml").is_file():
        return path
    params = replace(SynthParams(), board_volume=volume, closeups=closeups, **IMAGE_SETS[name])
    if name in IMAGES:
        base = ensure_set(data, layout, frames, seed, IMAGES[name], board, workers, volume,
                          closeups)
        _link_listed(path, base, layout, seed, params)
    else:
        print(f"rendering {path} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        synthesize(path, layout, frames, seed, board, params, workers=workers)
        print(f"  rendered in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return path


def _link_listed(path: Path, base: Path, layout: str, seed: int, params: SynthParams) -> None:
    """``base``'s images (symlinked) with the rig.yaml an intrinsics error writes."""
    rig = make_rig(layout, seed, params)
    gt = read_yaml_mapping(base / "ground_truth.yaml", "ground truth")
    for cam in rig.cameras:  # the error must only change what rig.yaml lists
        true = parse_camera(gt["intrinsics"][cam.name], cam.name)
        assert np.allclose(cam.intrinsics.K, true.K) and np.allclose(
            cam.intrinsics.dist, true.dist
        ), f"{cam.name}: true intrinsics differ from {base}"
    path.mkdir(parents=True, exist_ok=True)
    for cam in rig.cameras:
        link = path / cam.name
        if not link.exists():
            link.symlink_to(os.path.relpath(base / cam.name, path))
    save_rig(Rig({c.name: c.rig_intrinsics for c in rig.cameras}, rig.reference), path / "rig.yaml")
    gt["params"]["intrinsics_error"] = list(params.intrinsics_error)
    write_yaml(path / "ground_truth.yaml", gt)


# ----------------------------------------------------------------------------- one run
def intrinsics_error(
    model: CameraIntrinsics, true: CameraIntrinsics, corners: np.ndarray
) -> dict[str, float | None]:
    """Focal (%), centre (px) and reprojection (px: image / hull of ``corners``) errors."""
    u, v = np.meshgrid(
        np.linspace(0, true.width - 1, true.width // 8 + 1),
        np.linspace(0, true.height - 1, true.height // 8 + 1),
    )
    uv = np.column_stack([u.ravel(), v.ravel()])
    diff = np.linalg.norm(model.project(true.rays(uv[:, 0], uv[:, 1])) - uv, axis=1)
    covered = None
    if len(corners) >= 3:
        hull = cv2.convexHull(corners.astype(np.float32))[:, 0, :]
        inside = Polygon(hull).contains_points(uv)
        covered = float(diff[inside].max()) if inside.any() else None
    return {
        "fx_pct": abs(model.fx / true.fx - 1) * 100,
        "fy_pct": abs(model.fy / true.fy - 1) * 100,
        "cx_px": abs(model.cx - true.cx),
        "cy_px": abs(model.cy - true.cy),
        "image_px": float(diff.max()),
        "covered_px": covered,
    }


def run_method(
    method: str, path: Path, image_cache: Path, board: Board, workers: int
) -> dict[str, Any]:
    """One method on one set; never raises (a failure is a record with its traceback)."""
    rec: dict[str, Any] = {"method": method, "status": "ok", "message": ""}
    try:
        dataset, gt = FolderDataset(path), load_ground_truth(path)
        t0 = time.perf_counter()
        if method == "thesis":
            result = thesis_method(dataset, board, cache_dir=image_cache / "none", workers=workers)
        else:
            cache = image_cache / "edges"
            if method == "auto":  # the refined-lens detections depend on the set's rig.yaml
                cache = path.parent / "cache" / path.name / "auto"
                cache.mkdir(parents=True, exist_ok=True)
                (cache / "detections_refined_lens.json").unlink(missing_ok=True)
                shared = image_cache / "edges" / "detections.json"
                if shared.is_file() and not (cache / "detections.json").is_file():
                    shutil.copy(shared, cache / "detections.json")
            config = CalibrationConfig(
                workers=workers, refine="none", bundle=BundleConfig(intrinsics=method, board=method)
            )
            result = calibrate(dataset, board, config, cache_dir=cache)
        rec["wall_s"] = time.perf_counter() - t0
        rec["detection_s"] = result.timings_s.get("detection", 0.0)
        cams = result.extrinsics.cameras
        rec["kept"], rec["total"] = len(cams), len(dataset.cameras)
        rec["missing"] = dict(result.extrinsics.unconnected)
        rec["cameras"] = []
        for c, e in cams.items():
            if c == gt.reference:
                continue
            rot, mm = transform_error(e.T_ref_cam, gt.T_ref_cam[c])
            sigmas = dict(sigma_rotation_deg=e.sigma_rotation_deg, sigma_mm=e.sigma_translation_mm)
            nees = camera_record(c, e.T_ref_cam, gt.T_ref_cam[c], covariance=e.covariance)["nees"]
            rec["cameras"].append(dict(camera=c, rotation_deg=rot, translation_mm=mm, nees=nees,
                                       **sigmas))
        bundle = result.bundle
        if result.self_calibration is not None:
            rec["self_calibration"] = result.self_calibration.to_dict()
        if bundle is not None and bundle.board is not None and not bundle.board.held:
            rot, mm = transform_error(bundle.board.T_front_back, gt.T_front_back)
            T, c = bundle.board.T_front_back - gt.T_front_back, bundle.board.centre
            centre_mm = float(np.linalg.norm(T[:3, :3] @ c + T[:3, 3]) * 1000)  # at the grid
            rec["glue_error"] = {"translation_mm": mm, "rotation_deg": rot, "centre_mm": centre_mm}
        refined = dict(bundle.intrinsics) if bundle is not None else {}
        rec["intrinsics_refined"] = sorted(refined)
        rec["intrinsics"] = {}
        for c, true in gt.intrinsics.items():
            pts = [o.corners_px.reshape(-1, 2) for o in result.observations if o.camera == c]
            pts = np.concatenate(pts) if pts else np.zeros((0, 2))
            rec["intrinsics"][c] = intrinsics_error(
                refined.get(c, dataset.rig.cameras[c]), true, pts
            )
    except Exception as exc:
        rec["status"] = "failed"
        rec["message"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
        rec["traceback"] = traceback.format_exc()
    return rec


def cached_run(
    method: str, path: Path, image_cache: Path, board: Board, workers: int, rerun: bool
) -> tuple[dict[str, Any], bool]:
    gt = (path / "ground_truth.yaml").stat()
    key = [method, RECORD_VERSION, code_hash(), board.to_dict(), gt.st_mtime_ns]
    fingerprint = hashlib.sha256(json.dumps(key, default=str).encode()).hexdigest()[:16]
    cache_file = path.parent / "cache" / path.name / "results" / f"{method}.json"
    if not rerun and cache_file.is_file():
        saved = json.loads(cache_file.read_text())
        if saved.get("fingerprint") == fingerprint:
            return saved["record"], True
    rec = _rounded(run_method(method, path, image_cache, board, workers))
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(cache_file, json.dumps({"fingerprint": fingerprint, "record": rec}))
    return rec, False


# ----------------------------------------------------------------------------- tables
def _rms(xs: list[float]) -> float | None:
    return float(np.sqrt(np.mean(np.square(xs)))) if xs else None


def summary(recs: list[dict[str, Any]]) -> dict[str, Any]:
    """One (layout, set, method) over its seeds."""
    ok = [r for r in recs if r["status"] == "ok"]
    cams = [c for r in ok for c in r["cameras"]]
    mm = [c["translation_mm"] for c in cams]
    deg = [c["rotation_deg"] for c in cams]
    ints = [i for r in ok for i in r["intrinsics"].values()]
    glue = [r["glue_error"] for r in ok if "glue_error" in r]

    def worst(key: str, xs: list[dict[str, Any]]) -> float | None:
        vals = [x[key] for x in xs if x.get(key) is not None]
        return max(vals) if vals else None

    return {
        "kept": f"{sum(r['kept'] for r in ok)}/{sum(r['total'] for r in ok)}" if ok else "failed",
        "worst_mm": max(mm, default=None),
        "worst_deg": max(deg, default=None),
        "median_mm": float(np.median(mm)) if mm else None,
        "median_deg": float(np.median(deg)) if deg else None,
        "nrms_t": _rms([c["translation_mm"] / c["sigma_mm"] for c in cams if c["sigma_mm"]]),
        "nrms_r": _rms(
            [c["rotation_deg"] / c["sigma_rotation_deg"] for c in cams if c["sigma_rotation_deg"]]
        ),
        "nees_rms": (float(np.sqrt(np.mean(nees))) if (nees := [
            c["nees"] / 6.0 for c in cams if c.get("nees") is not None]) else None),
        "time_s": max((r["wall_s"] - r["detection_s"] for r in ok), default=None),
        "chosen": ", ".join(r.get("self_calibration", {}).get("chosen", "-") for r in ok) or "-",
        "refined": any(r["intrinsics_refined"] for r in ok),
        "glue_mm": worst("translation_mm", glue),
        "glue_deg": worst("rotation_deg", glue),
        "glue_centre_mm": worst("centre_mm", glue),
        **{
            k: worst(k, ints)
            for k in ("fx_pct", "fy_pct", "cx_px", "cy_px", "image_px", "covered_px")
        },
        "failures": [r["message"] for r in recs if r["status"] != "ok"],
    }


def markdown(payload: dict[str, Any]) -> str:
    meta, summ = payload["meta"], payload["summaries"]
    head = (
        "# Real-rig imperfections: fixed vs self-calibrating vs thesis\n\n"
        "Generated by tools/bench_imperfections.py (sets and methods: its docstring).\n\n"
        f"`{meta['command']}` ({meta['date']}, {meta['total_s']} s in all)\n\n"
        f"Seeds {meta['seeds']}, {meta['frames']} frame sets"
        + (f", board volume {meta['board_volume']:g} (synth --board-volume)"
           if meta.get("board_volume", 1.0) != 1.0 else "")
        + (f", {meta['closeups']} close-up frame sets per camera (synth --closeups)"
           if meta.get("closeups") else "")
        + ", synth noise defaults (blur "
        f"{meta['noise']['blur_sigma_px']} px, colour noise {meta['noise']['color_noise_dn']}"
        f" DN); load average {meta['load_start']} at start, {meta['load_end']} at the end "
        f"({meta['machine']}). Errors over the non-reference cameras; err/sigma is the RMS "
        "of error / claimed 1-sigma (translation / rotation), NEES the RMS of "
        "sqrt(xi^T C^-1 xi / 6) with the full 6x6 covariance (1 = honest); s is the wall "
        "time without the (cached) marker detection.\n\n"
    )
    cols = ("kept", "worst mm / deg", "err/sigma t / r / NEES", "s")
    ms = meta["methods"]
    lines = ["| layout | set | " + " | ".join(f"{m} {c}" for m in ms for c in cols) + " |"]
    lines.append("|---|---|" + "---|" * len(cols) * len(ms))
    auto = [
        "| layout | set | chosen | glue err mm / deg (at grid centre, mm) | fx / fy % | cx / cy px "
        "| lens worst px image / covered | rig.yaml: f %, c px, worst px image / covered |",
        "|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    for key in [f"{lay}/{n}" for lay in meta["layouts"] for n in meta["sets"]]:
        s = {m: summ[f"{key}/{m}"] for m in ms if f"{key}/{m}" in summ}
        if not s:
            continue
        row = "| " + key.replace("/", " | ") + " | "
        cells = []
        for m, x in s.items():
            cells += [x["kept"], f"{_f(x['worst_mm'])} / {_f(x['worst_deg'], 4)}"]
            cells += [f"{_f(x['nrms_t'], 2)} / {_f(x['nrms_r'], 2)} / {_f(x.get('nees_rms'), 2)}",
                      _f(x["time_s"], 1)]
            notes += [f"{key} {m}: {f}" for f in x["failures"]]
        lines.append(row + " | ".join(cells) + " |")
        if "auto" in s:
            a, f = s["auto"], s.get("fixed")
            lens = f"{_lens(a, ' | ', ' | ')}" if a["refined"] else "not refined | - | -"
            base = _lens(f, " %, ", " px, ") + " px" if f else "-"
            glue = f"{_f(a['glue_mm'])} / {_f(a['glue_deg'], 4)} ({_f(a['glue_centre_mm'])})"
            auto.append(f"{row}{a['chosen']} | {glue} | {lens} | {base} |")
    out = head + "\n".join(lines) + "\n\n`auto`: the model chosen and what it recovered "
    out += "(rig.yaml column: the listed model's error, what `fixed` calibrates with).\n\n"
    out += "\n".join(auto) + "\n"
    if notes:
        out += "\nFailures:\n\n" + "\n".join(f"- {n}" for n in notes) + "\n"
    return out


def _lens(x: dict[str, Any], sep1: str, sep2: str) -> str:
    return (
        f"{_f(x['fx_pct'], 3)} / {_f(x['fy_pct'], 3)}{sep1}{_f(x['cx_px'], 2)} / "
        f"{_f(x['cy_px'], 2)}{sep2}{_f(x['image_px'], 2)} / {_f(x['covered_px'], 2)}"
    )


def write(payload: dict[str, Any], args: argparse.Namespace) -> str:
    """Summaries (one per layout/set/method, over seeds), the JSON and the markdown."""
    meta, runs = payload["meta"], payload["runs"]
    keys = [(lay, n, m) for lay in meta["layouts"] for n in meta["sets"] for m in meta["methods"]]
    payload["summaries"] = {
        f"{lay}/{n}/{m}": summary(sel)
        for lay, n, m in keys
        if (sel := [r for r in runs if (r["layout"], r["set"], r["method"]) == (lay, n, m)])
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.json, json.dumps(_rounded(payload), indent=1))
    body = markdown(payload)
    if args.md:
        atomic_write_text(args.md, body)
    return body


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=Path("bench_data"), help="renders and caches")
    p.add_argument("--layouts", nargs="+", default=["race", "ring"], choices=["race", "ring"])
    p.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--seeds", nargs="+", type=int, default=[11])
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--board-volume", type=float, default=1.0,
                   help="synth --board-volume of every set (docs/synthetic.md)")
    p.add_argument("--closeups", type=int, default=0,
                   help="synth --closeups of every set: frame sets per camera with the board "
                   "near it, out to its image's corners (docs/synthetic.md)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--rerun", action="store_true", help="ignore cached results")
    p.add_argument("--json", type=Path, default=Path("docs/imperfections.json"))
    p.add_argument("--md", type=Path, default=None, help="markdown output (default: print)")
    p.add_argument("--from-json", type=Path, help="re-make the tables from this JSON only")
    args = p.parse_args(argv)
    if args.from_json:
        print(write(json.loads(args.from_json.read_text()), args))
        return 0
    board, synth, load = thesis_board(), SynthParams(), os.getloadavg
    cmd = " ".join(argv if argv is not None else sys.argv[1:])
    meta = dict(command=f"python tools/bench_imperfections.py {cmd}", layouts=args.layouts)
    meta.update(sets=args.sets, methods=args.methods, seeds=args.seeds, frames=args.frames)
    meta["board_volume"] = args.board_volume
    meta["closeups"] = args.closeups
    meta.update(sets_params=SETS, machine=f"{os.cpu_count()} cores, shared")
    meta["noise"] = dict(blur_sigma_px=synth.blur_sigma_px, color_noise_dn=synth.color_noise_dn)
    meta.update(load_start=[round(x, 1) for x in load()], date=time.strftime("%F"))
    payload: dict[str, Any] = {"meta": meta, "runs": []}
    t_start = time.perf_counter()
    for layout, seed, name in [
        (a, b, c) for a in args.layouts for b in args.seeds for c in args.sets
    ]:
        try:
            path = ensure_set(args.data, layout, args.frames, seed, name, board, args.workers,
                              args.board_volume, args.closeups)
        except Exception as exc:
            traceback.print_exc()
            fail = dict(layout=layout, seed=seed, set=name, status="failed")
            payload["runs"] += [
                {**fail, "method": m, "message": f"render: {exc}"} for m in args.methods
            ]
            continue
        image_cache = args.data / "cache" / set_name(
            layout, args.frames, seed, IMAGES.get(name, name), args.board_volume, args.closeups)
        for m in args.methods:
            t0 = time.perf_counter()
            rec, cached = cached_run(m, path, image_cache, board, args.workers, args.rerun)
            payload["runs"].append({**rec, "layout": layout, "seed": seed, "set": name})
            how = "cached" if cached else f"{time.perf_counter() - t0:.0f} s"
            print(
                f"{path.name:28s} {m:7s} {rec['status']} ({how}) {rec['message']}", file=sys.stderr
            )
            meta["load_end"] = [round(x, 1) for x in load()]
            meta["total_s"] = round(time.perf_counter() - t_start)
            body = write(payload, args)
    print(body)
    return 0


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
