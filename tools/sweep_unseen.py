"""A sweep of rigs never tuned on (issue 56, item 5): each rig drawn from its own seed (layout,
resolution, 12-24 frame sets, board speed 0-0.5 m/s, clock offsets 0-33 ms, global or rolling
shutter, with or without timestamps.csv, with or without D435 depth errors, still or moving),
rendered by ``synth``, calibrated by the default ``calibrate`` (``--refine none``, the board
alone, unless the rig has depth errors and is not a race16, or ``--depth-everywhere``) and
compared with its truth.

    python tools/sweep_unseen.py WORKDIR [--rigs 30] [--seed0 56100] [--json OUT.json]

Prints one row per rig: what was drawn, the verdict and exit code, the worst camera's
translation error (mm) against the bound of its layout, the RMS of error / sigma over the
cameras, the model the ladder chose with its held-out corner RMS against the simpler model's,
the bundle stage's seconds and, with depth errors, the worst camera's fused-cloud bias (mm).
A rig FAILS on a traceback (exit 1) or an error beyond 10x its bound under GOOD or CHECK;
else it is POOR (the verdict names the limit), honest (within its bound, RMS error/sigma <= 1.8
and no camera beyond 3 sigma), wider than the bound with honest sigmas, or GOOD/CHECK with
sigmas too small. Renders and results
are kept in WORKDIR (a re-run reuses the renders)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from toolmain import run_tool

from rgbd_calib.core.geometry import invert_transform, transform_error
from rgbd_calib.core.yamlio import read_yaml_mapping
from rgbd_calib.model.results import load_extrinsics

BOUND_MM = {"race": 1.0, "ring": 0.5, "race16": 2.0}  # the accuracy bounds of docs/
HONEST = 1.8  # RMS error / sigma at most this: the sigmas can be taken at face value
DE_FLAGS = ("--depth-bias", "--depth-disparity-offset", "--depth-disparity-field")


def draw(seed: int) -> dict[str, Any]:
    """One rig's settings from its seed."""
    rng = np.random.default_rng(seed)
    layout = str(rng.choice(["race", "ring", "race16"], p=[0.45, 0.45, 0.10]))
    res = {"race": ["848x480", "640x480", "1280x720"], "ring": ["1280x720", "848x480"],
           "race16": ["848x480"]}[layout]
    still = bool(rng.random() < 0.35)
    return {
        "seed": seed, "layout": layout, "resolution": str(rng.choice(res)),
        "frames": 16 if layout == "race16" else int(rng.integers(12, 25)),
        "speed_mps": 0.0 if still else round(float(rng.uniform(0.1, 0.5)), 2),
        "rate_dps": 0.0 if still else round(float(rng.uniform(10, 40)), 1),
        "offset_ms": round(float(rng.choice([0.0, rng.uniform(0, 33)])), 1),
        "rolling_ms": round(float(rng.choice([0.0, rng.uniform(15, 30)])), 1),
        "timestamps": bool(rng.random() < 0.5),
        "depth_errors": bool(rng.random() < 0.4),
        "de": [round(float(rng.uniform(0.002, 0.006)), 4), round(float(rng.uniform(0.05, 0.3)), 3),
               round(float(rng.uniform(0.02, 0.15)), 3), round(float(rng.uniform(0.1, 0.3)), 2),
               round(float(rng.uniform(0.5, 1.5)), 2)],
    }


def render(rig: dict[str, Any], folder: Path, log: Path) -> None:
    if (folder / "ground_truth.yaml").is_file():
        return
    args = ["synth", str(folder), "--layout", rig["layout"], "--frames", str(rig["frames"]),
            "--seed", str(rig["seed"]), "--resolution", rig["resolution"]]
    if rig["speed_mps"]:
        args += ["--motion", str(rig["speed_mps"]), str(rig["rate_dps"])]
    if rig["offset_ms"]:
        args += ["--sync-offset-ms", str(rig["offset_ms"])]
    if rig["rolling_ms"]:
        args += ["--rolling-shutter-ms", str(rig["rolling_ms"])]
    if rig["depth_errors"]:
        b, o, f, deg, mm = rig["de"]
        args += ["--depth-bias", str(b), "--depth-disparity-offset", str(o),
                 "--depth-disparity-field", str(f), "--depth-pose-error", str(deg), str(mm)]
    _run(args, log)
    if not rig["timestamps"]:
        for t in folder.glob("*/timestamps.csv"):
            t.unlink()


def _run(args: list[str], log: Path) -> int:
    with open(log, "a") as fh:
        fh.write("$ rgbd-calib " + " ".join(args) + "\n")
        fh.flush()
        exe = Path(sys.executable).parent / "rgbd-calib"  # the environment's entry point
        code = subprocess.run([str(exe), *args], stdout=fh,
                              stderr=subprocess.STDOUT).returncode
        fh.write(f"exit {code}\n")
        return code


def judge(rig: dict[str, Any], render_dir: Path, out: Path, code: int) -> dict[str, Any]:
    """The rig's row: errors against the truth, the ladder's choice, the verdict."""
    row: dict[str, Any] = {**rig, "exit": code}
    if not (out / "extrinsics.yaml").is_file():
        row["status"] = "FAIL (traceback)" if code == 1 else f"no result (exit {code})"
        return row
    truth = read_yaml_mapping(render_dir / "ground_truth.yaml", "ground truth")["T_ref_cam"]
    ext = load_extrinsics(out / "extrinsics.yaml")
    T_ref = np.asarray(truth[ext.reference], float)
    errs, z = {}, []
    for cam, e in ext.cameras.items():
        T_true = invert_transform(T_ref) @ np.asarray(truth[cam], float)
        deg, mm = transform_error(e.T_ref_cam, T_true)
        errs[cam] = mm
        if cam != ext.reference and e.sigma_translation_mm:
            z.append(mm / e.sigma_translation_mm)
    honest = bool(z) and float(np.sqrt(np.mean(np.square(z)))) <= HONEST and max(z) <= 3.0
    report = json.loads((out / "report.json").read_text())
    bundle = report.get("bundle") or {}
    ladder = (bundle.get("self_calibration") or {})
    levels = ladder.get("levels") or []
    accepted = [lv for lv in levels[1:] if lv["accepted"]]
    held = [lv["held_out"] for lv in accepted if lv.get("held_out")]
    grade = report["summary"]["verdict"]
    worst = max(errs.values())
    bound = BOUND_MM[rig["layout"]]
    rms_z = float(np.sqrt(np.mean(np.square(z)))) if z else float("nan")
    row |= {"verdict": grade, "worst_mm": worst, "bound_mm": bound, "rms_err_sigma": rms_z,
            "cameras": len(ext.cameras), "chosen": ladder.get("chosen"),
            "held_out": held, "bundle_s": (report.get("timings_s") or {}).get("bundle"),
            "errors": [w["code"] for w in report["warnings"] if w["severity"] == "error"]}
    if (out / "depth_model.yaml").is_file():
        row["depth_physical"] = physical(out / "depth_model.yaml",
                                         render_dir / "rig.yaml")
    if rig["depth_errors"] and (out / "fused.ply").is_file():
        sys.path.insert(0, str(Path(__file__).parent))
        from bench_fused import measure  # a benchmark's measure, not the package's
        biases = [abs(v["as-is"]["bias_mm"]) for v in
                  measure(out, render_dir, {"as-is": "as-is"}).values()
                  if v["as-is"]["bias_mm"] is not None]
        row["fused_bias_worst_mm"] = max(biases) if biases else None
    row["max_err_sigma"] = max(z) if z else None
    if grade != "poor" and worst > 10 * bound:
        row["status"] = "FAIL (beyond 10x the bound under " + grade.upper() + ")"
    elif grade == "poor":
        row["status"] = "POOR, named"
    elif worst <= bound and honest:
        row["status"] = "honest"
    elif honest:
        row["status"] = "wider than the bound, sigmas honest"
    else:
        row["status"] = "sigmas too small"  # GOOD or CHECK with errors beyond their sigmas
    return row


def physical(models_path: Path, rig_path: Path) -> bool:
    """Whether every camera's depth model gives a finite, positive depth increasing in the
    measured one at every pixel of its image for measured depths over 0.2-10 m."""
    from rgbd_calib.model.depth_model_file import load_depth_models
    from rgbd_calib.model.rig import load_rig
    rig = load_rig(rig_path)
    z = np.linspace(0.2, 10.0, 50)
    for cam, model in load_depth_models(models_path).items():
        intr = rig.cameras[cam]
        v, u = np.mgrid[0:intr.height:4, 0:intr.width:4]
        rays = intr.rays(u.ravel().astype(float), v.ravel().astype(float))
        depth = model.true_depth(rays[None, :, 0], rays[None, :, 1],
                                 np.broadcast_to(z[:, None], (len(z), len(rays))))
        if not (np.all(np.isfinite(depth)) and np.all(depth > 0)
                and np.all(np.diff(depth, axis=0) > 0)):
            return False
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--rigs", type=int, default=30)
    ap.add_argument("--seed0", type=int, default=56100)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--depth-everywhere", action="store_true",
                    help="the default depth stage on every rig (else only where the rig has "
                    "depth errors; the others with --refine none)")
    ap.add_argument("--judge-only", action="store_true",
                    help="judge the results already in WORKDIR again; render and run nothing")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for i in range(args.rigs):
        rig = draw(args.seed0 + i)
        name = f"rig{rig['seed']}"
        render_dir, out = args.workdir / name, args.workdir / f"{name}_out"
        log = args.workdir / f"{name}.log"
        done = (out / "report.json").is_file() and log.is_file()
        if args.judge_only or done:  # judged again from what is in WORKDIR
            if not (render_dir / "ground_truth.yaml").is_file():
                continue
            said = [ln for ln in log.read_text().splitlines() if ln.startswith("exit ")]
            code = int(said[-1].split()[1]) if said else 0
            row = judge(rig, render_dir, out, code)
        else:
            render(rig, render_dir, log)
            t0 = time.monotonic()
            # the depth stage where the rig has depth errors to test it on; the board's
            # extrinsics alone elsewhere (the depth stage costs 1-2 minutes a rig)
            depth = ([] if (rig["depth_errors"] and rig["layout"] != "race16")
                     or args.depth_everywhere else ["--refine", "none"])
            code = _run(["calibrate", str(render_dir), "--out", str(out), *depth], log)
            row = judge(rig, render_dir, out, code) | {"calibrate_s": time.monotonic() - t0}
        rows.append(row)
        print(_line(row), flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))
    failed = [r for r in rows if r["status"].startswith("FAIL")]
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    print(f"{len(rows)} rigs: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
    return 1 if failed else 0


def _line(r: dict[str, Any]) -> str:
    what = (f"{r['layout']:6s} {r['resolution']:>8s} {r['frames']:2d} sets "
            f"{r['speed_mps']:.2f} m/s {r['offset_ms']:4.1f} ms "
            f"{'RS' if r['rolling_ms'] else 'GS'} {'ts' if r['timestamps'] else '--'} "
            f"{'DE' if r['depth_errors'] else '--'}")
    if "verdict" not in r:
        return f"{r['seed']} {what}: {r['status']}"
    held = "; ".join(f"{h['rms_before_px']:.3f}->{h['rms_after_px']:.3f}" for h in r["held_out"])
    fused = (f" fused {r['fused_bias_worst_mm']:.2f} mm" if r.get("fused_bias_worst_mm")
             is not None else "")
    return (f"{r['seed']} {what}: {r['verdict'].upper():5s} exit {r['exit']} worst "
            f"{r['worst_mm']:.3f} mm (bound {r['bound_mm']}) err/sigma {r['rms_err_sigma']:.2f} "
            f"chosen [{r['chosen']}] held-out {held or '-'} bundle {r['bundle_s'] or 0:.0f} s"
            f"{fused} -> {r['status']}")


if __name__ == "__main__":
    run_tool(main)
