"""Cut a two-camera test sample out of a TUM RGB-D benchmark sequence (real Kinect data with
motion-capture ground truth).

    python tools/make_real_rgbd_sample.py PATH/rgbd_dataset_freiburg1_xyz \\
        --out tests/data/tum_fr1_xyz_pair

``PATH`` is a sequence as TUM publishes it (a folder with ``rgb.txt``, ``depth.txt``,
``groundtruth.txt``, ``rgb/`` and ``depth/``, or the ``.tgz`` itself). Two RGB-D frames of the
moving Kinect become two cameras ``a`` and ``b`` of the project's folder form
(docs/formats.md)::

    <out>/rig.yaml                      a and b, same intrinsics, depth_scale 0.0002 (1/5000 m),
                                        depth_noise kinect-v1
    <out>/a/color/000000.png            the TUM files, copied byte for byte
    <out>/a/depth/000000.png
    <out>/b/color/000000.png
    <out>/b/depth/000000.png
    <out>/ground_truth.yaml             T_ref_cam {a: I, b: T_a_b} from the mocap poses
    <out>/init_extrinsics.yaml          b moved --offset-cm / --offset-deg off the truth (seeded)
    <out>/README.md                     source, licence (CC BY 4.0), citation, frame choice

Conventions (TUM "File Formats" page): ``groundtruth.txt`` rows are
``timestamp tx ty tz qx qy qz qw``, the pose of the colour camera's optical centre in the
mocap world, i.e. ``T_world_cam`` of the optical frame (x right, y down, z forward) that
formats.md uses, so ``T_a_b = inv(T_world_a) @ T_world_b``. Depth PNGs are 16-bit with 5000
counts per metre, already registered to the colour image by the OpenNI driver. The mocap runs
at 100 Hz: a frame's pose is interpolated (linear / slerp) at its **depth** timestamp (the
geometry ICP aligns), and a frame is used only when mocap samples lie within ``--max-gt-gap``
on both sides. Colour and depth are associated by nearest timestamp (``--max-dt``, TUM's
associate.py uses 20 ms).

Intrinsics: ``ros-default`` (fx = fy = 525, cx = 319.5, cy = 239.5, no distortion; what TUM
recommends for the pre-registered depth) or the calibrated colour intrinsics ``fr1`` /
``fr2`` / ``fr3`` from the TUM page.

Frame choice (``--pair I J`` picks associated frames by index): otherwise every pair whose
relative motion lies in ``--min-move-m``..``--max-move-m`` and ``--min-rot-deg``..
``--max-rot-deg`` is a candidate; the slowest-moving ones (mocap speed, colour-depth time
offset) are scored by depth overlap (frame a's depth re-projected into b agrees with b's depth
within 3 cm, both ways) and the best is taken. Deterministic.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import shutil
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    matrix_to_quaternion_xyzw,
    quaternion_xyzw_to_matrix,
    rotation_angle_deg,
    rotvec_to_matrix,
)
from rgbd_calib.core.yamlio import write_yaml
from rgbd_calib.model.results import CameraExtrinsics, Extrinsics, write_extrinsics

DEPTH_COUNTS_PER_M = 5000.0  # TUM RGB-D depth PNGs (File Formats page)
WIDTH, HEIGHT = 640, 480
# TUM "Camera Calibration" page; 'ros-default' is recommended there for the registered depth.
INTRINSICS = {
    "ros-default": (525.0, 525.0, 319.5, 239.5, [0.0, 0.0, 0.0, 0.0, 0.0]),
    "fr1": (517.3, 516.5, 318.6, 255.3, [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "fr2": (520.9, 521.0, 325.1, 249.7, [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "fr3": (535.4, 539.2, 320.1, 247.6, [0.0, 0.0, 0.0, 0.0, 0.0]),
}
LICENCE = "CC BY 4.0 (https://creativecommons.org/licenses/by/4.0/)"
CITATION = (
    "J. Sturm, N. Engelhard, F. Endres, W. Burgard and D. Cremers, \"A Benchmark for the "
    "Evaluation of RGB-D SLAM Systems\", Proc. of the International Conference on Intelligent "
    "Robot Systems (IROS), 2012."
)


# --------------------------------------------------------------------------- TUM files
def read_list(path: Path) -> list[tuple[float, list[str]]]:
    """``timestamp rest...`` rows of a TUM text file ('#' lines are comments)."""
    rows = []
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        rows.append((float(parts[0]), parts[1:]))
    rows.sort(key=lambda r: r[0])
    return rows


def associate(a: list[float], b: list[float], max_dt: float) -> list[tuple[int, int]]:
    """One-to-one nearest-timestamp matching, closest pairs first (TUM associate.py)."""
    b_arr = np.asarray(b)
    cands = []
    for i, t in enumerate(a):
        lo = np.searchsorted(b_arr, t - max_dt)
        hi = np.searchsorted(b_arr, t + max_dt, side="right")
        cands += [(abs(t - b_arr[j]), i, j) for j in range(lo, hi)]
    cands.sort()
    used_a, used_b, out = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - s) * th) * q0 + math.sin(s * th) * q1) / math.sin(th)


class Trajectory:
    """The mocap trajectory of ``groundtruth.txt`` (``T_world_cam``, optical frame)."""

    def __init__(self, rows: list[tuple[float, list[str]]]):
        self.t = np.array([r[0] for r in rows])
        vals = np.array([[float(x) for x in r[1][:7]] for r in rows])
        self.p, self.q = vals[:, :3], vals[:, 3:7]  # tx ty tz, qx qy qz qw

    def pose(self, t: float, max_gap: float) -> np.ndarray | None:
        """Interpolated ``T_world_cam`` at ``t``; None without samples within ``max_gap`` on
        both sides (mocap dropout, or outside the recorded span)."""
        k = int(np.searchsorted(self.t, t))
        if k == 0 or k >= self.t.size:
            return None
        t0, t1 = self.t[k - 1], self.t[k]
        if t - t0 > max_gap or t1 - t > max_gap:
            return None
        s = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
        p = (1 - s) * self.p[k - 1] + s * self.p[k]
        q = slerp(self.q[k - 1], self.q[k], s)
        return make_transform(quaternion_xyzw_to_matrix(q), p)

    def speed(self, t: float, half_window: float = 0.05) -> tuple[float, float]:
        """Linear (m/s) and angular (deg/s) speed around ``t`` from the mocap samples."""
        a = self.pose(t - half_window, 1.0)
        b = self.pose(t + half_window, 1.0)
        if a is None or b is None:
            return math.inf, math.inf
        d = invert_transform(a) @ b
        return (float(np.linalg.norm(d[:3, 3])) / (2 * half_window),
                rotation_angle_deg(d[:3, :3]) / (2 * half_window))


@dataclass(frozen=True)
class Frame:
    index: int
    t_rgb: float
    rgb: str
    t_depth: float
    depth: str
    T_world_cam: np.ndarray
    speed_m_s: float
    speed_deg_s: float


def load_frames(seq: Path, max_dt: float, max_gt_gap: float) -> list[Frame]:
    rgb = read_list(seq / "rgb.txt")
    depth = read_list(seq / "depth.txt")
    traj = Trajectory(read_list(seq / "groundtruth.txt"))
    frames = []
    for i, j in associate([r[0] for r in rgb], [d[0] for d in depth], max_dt):
        t_d = depth[j][0]
        T = traj.pose(t_d, max_gt_gap)
        if T is None:
            continue
        v, w = traj.speed(t_d)
        frames.append(Frame(len(frames), rgb[i][0], rgb[i][1][0], t_d, depth[j][1][0], T, v, w))
    return frames


# --------------------------------------------------------------------------- frame choice
def relative(fa: Frame, fb: Frame) -> np.ndarray:
    return invert_transform(fa.T_world_cam) @ fb.T_world_cam


def depth_points(path: Path, K: np.ndarray, step: int = 4) -> np.ndarray:
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16:
        raise SystemExit(f"{path}: not a 16-bit depth PNG")
    vs, us = np.mgrid[0:d.shape[0]:step, 0:d.shape[1]:step]
    z = d[vs, us].astype(float) / DEPTH_COUNTS_PER_M
    ok = z > 0
    x = (us[ok] - K[0, 2]) / K[0, 0] * z[ok]
    y = (vs[ok] - K[1, 2]) / K[1, 1] * z[ok]
    return np.column_stack([x, y, z[ok]])


def overlap(pts_a: np.ndarray, depth_b: np.ndarray, T_b_a: np.ndarray, K: np.ndarray,
            tol_m: float = 0.03) -> float:
    """Fraction of a's points that b sees at the same depth (within ``tol_m``)."""
    p = pts_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(K[0, 0] * p[:, 0] / z + K[0, 2])
        v = np.rint(K[1, 1] * p[:, 1] / z + K[1, 2])
    ok = (z > 0.1) & (u >= 0) & (u < depth_b.shape[1]) & (v >= 0) & (v < depth_b.shape[0])
    zb = np.zeros_like(z)
    zb[ok] = depth_b[v[ok].astype(int), u[ok].astype(int)] / DEPTH_COUNTS_PER_M
    agree = ok & (zb > 0) & (np.abs(zb - z) < tol_m)
    return float(agree.sum()) / max(len(p), 1)


def choose_pair(seq: Path, frames: list[Frame], args, K: np.ndarray) -> tuple[int, int, float]:
    if args.pair:
        i, j = args.pair
        return i, j, math.nan
    cands = []
    for i, fa in enumerate(frames):
        if abs(fa.t_rgb - fa.t_depth) > args.max_rgb_depth_dt:
            continue
        for fb in frames[i + 1:]:
            if abs(fb.t_rgb - fb.t_depth) > args.max_rgb_depth_dt:
                continue
            T = relative(fa, fb)
            move = float(np.linalg.norm(T[:3, 3]))
            rot = rotation_angle_deg(T[:3, :3])
            if not (args.min_move_m <= move <= args.max_move_m
                    and args.min_rot_deg <= rot <= args.max_rot_deg):
                continue
            # slow frames first: less motion blur, rolling shutter and colour-depth skew
            cost = max(fa.speed_m_s, fb.speed_m_s) / 0.1 + max(fa.speed_deg_s,
                                                                  fb.speed_deg_s) / 10.0
            cands.append((cost, fa.index, fb.index))
    if not cands:
        raise SystemExit("no frame pair moves within the requested ranges; widen them")
    cands.sort()
    best = None
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def load(k: int):
        if k not in cache:
            p = seq / frames[k].depth
            cache[k] = (depth_points(p, K), cv2.imread(str(p), cv2.IMREAD_UNCHANGED))
        return cache[k]

    for _, i, j in cands[: args.candidates]:
        (pa, da), (pb, db) = load(i), load(j)
        T_b_a = invert_transform(relative(frames[i], frames[j]))
        score = min(overlap(pa, db, T_b_a, K), overlap(pb, da, invert_transform(T_b_a), K))
        if best is None or score > best[2]:
            best = (i, j, score)
    return best


# --------------------------------------------------------------------------- writing
def perturb(T: np.ndarray, cm: float, deg: float, seed: int) -> np.ndarray:
    """``T @ [R(axis, deg) | d]`` with a seeded random axis and direction, |d| = cm."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    d = rng.normal(size=3)
    return T @ make_transform(rotvec_to_matrix(axis / np.linalg.norm(axis) * math.radians(deg)),
                              d / np.linalg.norm(d) * cm / 100.0)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_sample(seq: Path, frames: list[Frame], i: int, j: int, score: float, args) -> None:
    out: Path = args.out
    if out.exists():
        shutil.rmtree(out)
    fx, fy, cx, cy, dist = INTRINSICS[args.intrinsics]
    cam = {"width": WIDTH, "height": HEIGHT, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
           "distortion": dist, "depth_scale": 1.0 / DEPTH_COUNTS_PER_M,
           "depth_noise": "kinect-v1"}  # structured light: not the D435 stereo model
    fa, fb = frames[i], frames[j]
    for name, f in (("a", fa), ("b", fb)):
        for kind, rel in (("color", f.rgb), ("depth", f.depth)):
            dst = out / name / kind / "000000.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(seq / rel, dst)
    write_yaml(out / "rig.yaml", {"reference": "a", "cameras": {"a": cam, "b": dict(cam)}})
    T_a_b = relative(fa, fb)
    src = {
        "sequence": seq.name,
        "intrinsics": args.intrinsics,
        "pose_time": "depth timestamp (mocap interpolated)",
    }
    for name, f in (("a", fa), ("b", fb)):
        src[name] = {"rgb": f.rgb, "depth": f.depth, "t_rgb": f.t_rgb, "t_depth": f.t_depth,
                     "T_world_cam": f.T_world_cam.tolist(),
                     "speed_m_s": round(f.speed_m_s, 4), "speed_deg_s": round(f.speed_deg_s, 3)}
    write_yaml(out / "ground_truth.yaml", {
        "reference": "a",
        "T_ref_cam": {"a": np.eye(4).tolist(), "b": T_a_b.tolist()},
        "T_ref_board": {},
        "depth_scale_bias": {"a": 1.0, "b": 1.0},
        "source": src,
    })
    T_init = perturb(T_a_b, args.offset_cm, args.offset_deg, args.seed)
    write_extrinsics(Extrinsics("a", {"a": CameraExtrinsics("a", np.eye(4)),
                                      "b": CameraExtrinsics("b", T_init)}),
                     out / "init_extrinsics.yaml")
    move = float(np.linalg.norm(T_a_b[:3, 3]))
    rot = rotation_angle_deg(T_a_b[:3, :3])
    q = matrix_to_quaternion_xyzw(T_a_b[:3, :3])
    files = sorted(p for p in out.rglob("*.png"))
    lines = [
        f"# Real RGB-D pair: TUM RGB-D `{seq.name}`",
        "",
        "Two frames of a hand-held Microsoft Kinect (v1) from the TUM RGB-D benchmark, used as "
        "two cameras `a` (reference) and `b` of a rig; the true `T_a_b` comes from the "
        "benchmark's motion-capture ground truth. Made by `tools/make_real_rgbd_sample.py` "
        "(see its docstring for the conventions); the PNGs are the benchmark's files, "
        "unchanged, renamed.",
        "",
        "## Source, licence, citation",
        "",
        f"- Data: TUM RGB-D benchmark, sequence `{seq.name}` "
        "(Computer Vision Group, Technical University of Munich).",
        f"- Licence: {LICENCE}. Changes: two frames selected and renamed; nothing else.",
        f"- Cite: {CITATION}",
        "",
        "## Frames",
        "",
        "| camera | colour file | t colour (s) | depth file | t depth (s) |",
        "| --- | --- | --- | --- | --- |",
        f"| a | `{fa.rgb}` | {fa.t_rgb:.6f} | `{fa.depth}` | {fa.t_depth:.6f} |",
        f"| b | `{fb.rgb}` | {fb.t_rgb:.6f} | `{fb.depth}` | {fb.t_depth:.6f} |",
        "",
        f"- Relative motion (mocap): {move * 100:.1f} cm, {rot:.1f} deg; "
        f"T_a_b translation {np.round(T_a_b[:3, 3], 4).tolist()} m, "
        f"quaternion xyzw {np.round(q, 5).tolist()}.",
        "- Depth overlap (a in b and b in a, within 3 cm, the smaller): "
        + ("not measured (pair given)" if math.isnan(score) else f"{score:.2f}") + ".",
        f"- Intrinsics `{args.intrinsics}`: fx {fx}, fy {fy}, cx {cx}, cy {cy}, "
        f"distortion {dist}; depth_scale 0.0002 m per count (5000 counts per metre).",
        f"- `init_extrinsics.yaml`: b moved {args.offset_cm} cm and {args.offset_deg} deg off "
        f"the truth (seed {args.seed}).",
        "",
        "## Files (sha256)",
        "",
    ]
    lines += [f"- `{p.relative_to(out).as_posix()}` {p.stat().st_size} B "
              f"`{sha256(p)[:16]}`" for p in files]
    (out / "README.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {out}: frames {fa.rgb} / {fb.rgb}, {move * 100:.1f} cm, {rot:.1f} deg, "
          f"overlap {score:.2f}, {sum(p.stat().st_size for p in files) / 1e6:.2f} MB of PNG")


def open_sequence(path: Path, tmp: Path) -> Path:
    """A sequence folder (the .tgz is extracted into ``tmp`` first)."""
    if path.is_dir():
        return path
    if not tarfile.is_tarfile(path):
        raise SystemExit(f"{path}: neither a TUM sequence folder nor its .tgz")
    with tarfile.open(path) as tar:
        tar.extractall(tmp, filter="data")
    dirs = [p.parent for p in tmp.rglob("groundtruth.txt")]
    if len(dirs) != 1:
        raise SystemExit(f"{path}: expected one sequence with groundtruth.txt, found {len(dirs)}")
    return dirs[0]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path, help="TUM sequence folder or its .tgz")
    ap.add_argument("--out", type=Path, required=True, help="sample folder to (re)write")
    ap.add_argument("--intrinsics", choices=sorted(INTRINSICS), default="ros-default")
    ap.add_argument("--pair", type=int, nargs=2, metavar=("I", "J"),
                    help="associated-frame indices to use instead of the automatic choice")
    ap.add_argument("--min-move-m", type=float, default=0.10)
    ap.add_argument("--max-move-m", type=float, default=0.30)
    ap.add_argument("--min-rot-deg", type=float, default=5.0)
    ap.add_argument("--max-rot-deg", type=float, default=15.0)
    ap.add_argument("--max-dt", type=float, default=0.02, help="colour-depth association (s)")
    ap.add_argument("--max-rgb-depth-dt", type=float, default=0.01,
                    help="automatic choice: largest colour-depth time offset of a frame (s)")
    ap.add_argument("--max-gt-gap", type=float, default=0.02,
                    help="mocap samples needed within this (s) on both sides of a frame")
    ap.add_argument("--candidates", type=int, default=40,
                    help="automatic choice: slowest pairs scored by depth overlap")
    ap.add_argument("--offset-cm", type=float, default=2.0)
    ap.add_argument("--offset-deg", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    fx, fy, cx, cy, _ = INTRINSICS[args.intrinsics]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    with tempfile.TemporaryDirectory() as tmp:
        seq = open_sequence(args.sequence, Path(tmp))
        frames = load_frames(seq, args.max_dt, args.max_gt_gap)
        if len(frames) < 2:
            raise SystemExit(f"{seq}: fewer than 2 frames with colour, depth and mocap pose")
        i, j, score = choose_pair(seq, frames, args, K)
        write_sample(seq, frames, i, j, score, args)
    return 0


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
