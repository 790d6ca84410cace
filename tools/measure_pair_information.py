"""Issue 14 item 2: how honest each pair's information is, on a synthetic rig with ground truth.

Usage: python tools/measure_pair_information.py DATASET PERTURB_MM PERTURB_DEG [key=value ...]
(DepthConfig overrides, e.g. information_patch_m=0.3; ``calibration=OUT`` back-projects with
OUT/rig_refined.yaml and gives each cloud the variances of its refined intrinsics from
OUT/report.json, times lens_sigma_factor, as calibrate does).
"""
import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

from rgbd_calib.core.config import DepthConfig
from rgbd_calib.core.geometry import invert_transform, make_transform, rotvec_to_matrix
from rgbd_calib.depth import clouds as DC
from rgbd_calib.depth import information as DI
from rgbd_calib.depth import registration as D
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.model.rig import load_rig
from rgbd_calib.synth.render import load_ground_truth


def main(path, perturb_mm, perturb_deg, method="colored-icp", max_frames=15, calibration=None,
         **cfg):
    ds, gt = FolderDataset(path), load_ground_truth(path)
    config = DepthConfig(max_frames=max_frames, **cfg)
    variances = {}
    if calibration is not None:
        ds = copy.copy(ds)
        ds.rig = load_rig(Path(calibration) / "rig_refined.yaml")
        report = json.loads((Path(calibration) / "report.json").read_text())
        variances = {c: {k: (config.uncertainty.lens_sigma_factor * v["sigma"]) ** 2
                         for k, v in (cam.get("intrinsics_refined") or {}).items()}
                     for c, cam in report["cameras"].items()}
    clouds = {c: DC.static_cloud(ds, c, gt.T_ref_board, gt.T_ref_cam[c], thesis_board(), config,
                                depth_scale_factor=gt.depth_scale_bias.get(c, 1.0))
              for c in ds.cameras}
    clouds = {c: D.replace(cl, intrinsics_variance=variances.get(c, {}))
              for c, cl in clouds.items()}
    pairs = D.find_overlapping_pairs(clouds, gt.T_ref_cam, None, config)
    rng = np.random.default_rng(1)
    zs = []
    for ov in pairs:
        a, b = ov.cam_a, ov.cam_b
        ax = rng.normal(size=3)
        d = rng.normal(size=3)
        T_ref_a = gt.T_ref_cam[a] @ make_transform(
            rotvec_to_matrix(ax / np.linalg.norm(ax) * np.radians(perturb_deg)),
            d / np.linalg.norm(d) * perturb_mm / 1000)
        t = time.perf_counter()
        reg = D.register_pair(clouds[a], clouds[b], T_ref_a, gt.T_ref_cam[b], method, config)
        xi = DI.tangent_error(reg.T_b_a, invert_transform(gt.T_ref_cam[b]) @ gt.T_ref_cam[a])
        info = reg.information
        if np.any(info):
            L = np.linalg.cholesky(info)
            z = L.T @ xi
            zs.append(z)
        else:
            z = np.full(6, np.nan)
        cov = np.linalg.pinv(info) if np.any(info) else np.full((6, 6), np.nan)
        sig = np.sqrt(np.abs(np.diag(cov)))
        err_mm, err_deg = 1000 * np.linalg.norm(xi[3:]), np.degrees(np.linalg.norm(xi[:3]))
        sig_mm, sig_deg = 1000 * np.linalg.norm(sig[3:]), np.degrees(np.linalg.norm(sig[:3]))
        print(f"{a:>6}-{b:<6} acc={int(reg.accepted)} err={err_mm:.2f}mm/{err_deg:.4f}deg "
              f"sig_t={sig_mm:.2f}mm sig_r={sig_deg:.4f}deg rmsz={np.sqrt(np.mean(z**2)):.2f} "
              f"nrms={reg.normalised_rms:.2f} chi2={reg.improvement_chi2:.1f} "
              f"patches={reg.n_patches} "
              f"cond={reg.conditioning:.3f} t={time.perf_counter()-t:.1f}s "
              f"{'' if reg.accepted else reg.reason}", flush=True)
    zs = np.array(zs)
    print("RMS(error/sigma) all components:", float(np.sqrt(np.mean(zs**2))),
          "per component:", np.sqrt(np.mean(zs**2, axis=0)).round(2))


def cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a synthetic render (synth's folder)")
    ap.add_argument("perturb_mm", type=float)
    ap.add_argument("perturb_deg", type=float)
    ap.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                    help="DepthConfig overrides, or calibration=OUT")
    args = ap.parse_args()
    kw = dict(a.split("=", 1) for a in args.overrides)
    kw = {k: (v if k == "calibration" else float(v) if "." in v else int(v) if v.isdigit()
              else v) for k, v in kw.items()}
    main(args.dataset, args.perturb_mm, args.perturb_deg, **kw)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    from toolmain import run_tool

    run_tool(cli)
