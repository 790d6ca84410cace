"""Speed benchmark: detection throughput and total calibration time against decoding alone.

    python tools/bench_speed.py --data bench_data --md docs/benchmarks.md

On a 4-camera x 400-frame 1280x720 synthetic set (thesis-line layout, rendered once and cached
under ``--data``) and for each worker count, repeated ``--repeats`` times:

- ``decode``: ``cv2.imread`` of every colour image (BGR, as a user would read them) in the
  same number of processes, started and chunked like the detection stage's pool (forkserver,
  4 images per task); the floor any pipeline that reads the PNGs has to pay;
- ``calibrate``: ``rgbd_calib.calibrate`` end to end with the default config (edge corners,
  bundle adjustment) and no detection cache; its detection stage gives the throughput.
  ``--refine none`` (default here) leaves out the depth stage (colored ICP), which is not
  part of the board calibration measured here; ``--refine auto`` includes it.

The ratio calibrate / decode is taken within each repetition (same machine state), then the
median over repetitions is reported. One untimed decode pass first puts the PNGs in the page
cache, so both sides read from memory. The machine's load average is recorded with every
run: on a shared machine other processes slow both sides alike, the ratio less so.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import cv2

from rgbd_calib.board import thesis_board
from rgbd_calib.calibrate import CalibrationConfig, calibrate
from rgbd_calib.dataset import FolderDataset
from rgbd_calib.parallel import process_context
from rgbd_calib.synth import SynthParams, synthesize

MD_BEGIN, MD_END = "<!-- bench_speed:begin -->", "<!-- bench_speed:end -->"
STAGE_ORDER = ("detection", "pose", "pose_graph", "bundle", "depth", "joint")


def _stages(rows: list[dict[str, Any]]) -> list[str]:
    found = {k for r in rows for k in r["stages_s"]}
    return [k for k in STAGE_ORDER if k in found] + sorted(found - set(STAGE_ORDER))


LAYOUT, SEED = "thesis-line", 0


def _decode(path: str) -> int:
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise RuntimeError(f"{path}: unreadable")
    return int(img.shape[0])


def decode_all(paths: list[str], workers: int) -> float:
    """Seconds to decode every image with ``workers`` processes (1: in this process)."""
    t0 = time.perf_counter()
    if workers <= 1:
        for p in paths:
            _decode(p)
    else:
        with ProcessPoolExecutor(workers, mp_context=process_context()) as ex:
            for _ in ex.map(_decode, paths, chunksize=4):
                pass
    return time.perf_counter() - t0


def ensure_dataset(data: Path, frames: int, workers: int) -> Path:
    path = data / f"{LAYOUT}-f{frames}-s{SEED}"
    if not (path / "ground_truth.yaml").is_file():
        print(f"rendering {path} (once) ...", file=sys.stderr, flush=True)
        synthesize(path, LAYOUT, frames, SEED, thesis_board(), SynthParams(), workers=workers)
    return path


def run(path: Path, workers_list: list[int], repeats: int, refine: str) -> dict[str, Any]:
    dataset = FolderDataset(path)
    board = thesis_board()
    paths = [str(p) for fs in dataset.frame_sets() for p in fs.color.values()]
    n = len(paths)
    decode_all(paths, max(workers_list))  # warm the page cache, untimed
    rows = []
    for workers in workers_list:
        for rep in range(repeats):
            load_before = os.getloadavg()[0]
            decode_s = decode_all(paths, workers)
            t0 = time.perf_counter()
            result = calibrate(dataset, board, CalibrationConfig(workers=workers, refine=refine))
            calibrate_s = time.perf_counter() - t0
            row = {
                "workers": workers,
                "repeat": rep,
                "images": n,
                "decode_s": decode_s,
                "calibrate_s": calibrate_s,
                "stages_s": dict(result.timings_s),
                "detection_images_per_s": n / result.timings_s["detection"],
                "decode_images_per_s": n / decode_s,
                "ratio": calibrate_s / decode_s,
                "load_before": load_before,
                "load_after": os.getloadavg()[0],
                "cameras": len(result.extrinsics.cameras),
                "observations": len(result.observations),
            }
            rows.append(row)
            print(
                f"workers {workers} run {rep}: decode {decode_s:.1f} s, calibrate "
                f"{calibrate_s:.1f} s (detection {result.timings_s['detection']:.1f} s), "
                f"ratio {row['ratio']:.2f}, load {load_before:.1f}->{row['load_after']:.1f}",
                file=sys.stderr,
                flush=True,
            )
    return {"images": n, "rows": rows}


def summary(rows: list[dict[str, Any]], workers: int) -> dict[str, float]:
    sel = [r for r in rows if r["workers"] == workers]
    med = statistics.median
    stages = _stages(sel)
    return {
        "runs": len(sel),
        "decode_s": med(r["decode_s"] for r in sel),
        "decode_images_per_s": med(r["decode_images_per_s"] for r in sel),
        "calibrate_s": med(r["calibrate_s"] for r in sel),
        "detection_images_per_s": med(r["detection_images_per_s"] for r in sel),
        "ratio": med(r["ratio"] for r in sel),
        "ratio_min": min(r["ratio"] for r in sel),
        "ratio_max": max(r["ratio"] for r in sel),
        "load": med(r["load_before"] for r in sel),
        **{f"stage_{k}_s": med(r["stages_s"].get(k, 0.0) for r in sel) for k in stages},
    }


def markdown(payload: dict[str, Any]) -> str:
    meta, rows = payload["meta"], payload["rows"]
    stages = _stages(rows)
    lines = [
        f"Generated by `{meta['command']}` on {meta['machine']} ({meta['date']}); "
        f"{payload['images']} colour images (4 cameras x {meta['frames']} frames, 1280x720 "
        f"PNG, thesis-line layout, seed {SEED}); calibration = default config with refine="
        f"{meta.get('refine', 'none')!r} (edge corners, bundle adjustment"
        f"{', no depth stage' if meta.get('refine', 'none') == 'none' else ''}), no "
        f"detection cache; medians of {meta['repeats']} runs. The ratio is "
        "calibrate / decode within each run (min-max in brackets). Load: the machine's "
        "1-minute load average before the runs (a shared 2-core machine; above 2 other "
        "processes were competing).",
        "",
        "| workers | decode (s) | decode (img/s) | detection (img/s) | calibrate total (s) | "
        + " | ".join(f"{s} (s)" for s in stages)
        + " | calibrate / decode | load |",
        "|---" * (7 + len(stages)) + "|",
    ]
    for w in meta["workers"]:
        s = summary(rows, w)
        lines.append(
            f"| {w} | {s['decode_s']:.1f} | {s['decode_images_per_s']:.0f} | "
            f"{s['detection_images_per_s']:.1f} | {s['calibrate_s']:.1f} | "
            + " | ".join(f"{s[f'stage_{k}_s']:.1f}" for k in stages)
            + f" | {s['ratio']:.1f} ({s['ratio_min']:.1f}-{s['ratio_max']:.1f}) | "
            f"{s['load']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def write_markdown(path: Path, body: str) -> None:
    """Replace the block between the markers of ``path``; append a Speed section if absent."""
    block = f"{MD_BEGIN}\n{body}{MD_END}\n"
    text = path.read_text() if path.is_file() else "# Benchmarks\n"
    if MD_BEGIN in text and MD_END in text:
        head, rest = text.split(MD_BEGIN, 1)
        tail = rest.split(MD_END, 1)[1].lstrip("\n")
        text = head + block + ("\n" + tail if tail else "")
    else:
        text = text.rstrip() + "\n\n## Speed\n\n" + block
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--data", type=Path, default=Path("bench_data"), help="folder of the rendered set (reused)"
    )
    p.add_argument("--frames", type=int, default=400)
    p.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--refine",
        default="none",
        choices=["none", "auto", "colored-icp", "geometric"],
        help="depth stage of the calibration (default: none, board only)",
    )
    p.add_argument("--json", type=Path, default=Path("docs/speed.json"))
    p.add_argument(
        "--md",
        type=Path,
        default=None,
        help="markdown file whose Speed block is replaced (e.g. docs/benchmarks.md)",
    )
    p.add_argument(
        "--from-json", type=Path, default=None, help="re-make the table from this JSON; run nothing"
    )
    args = p.parse_args(argv)
    if args.from_json:
        payload = json.loads(args.from_json.read_text())
    else:
        path = ensure_dataset(args.data, args.frames, max(args.workers))
        payload = run(path, args.workers, args.repeats, args.refine)
        payload["meta"] = {
            "command": "python tools/bench_speed.py "
            + " ".join(argv if argv is not None else sys.argv[1:]),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}, OpenCV {cv2.__version__}",
            "date": time.strftime("%Y-%m-%d"),
            "frames": args.frames,
            "workers": args.workers,
            "repeats": args.repeats,
            "dataset": str(path),
            "refine": args.refine,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(payload, indent=1))
    body = markdown(payload)
    print(body)
    if args.md:
        write_markdown(args.md, body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
