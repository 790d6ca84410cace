"""The whole default ``calibrate`` against its floor: decoding every colour and depth image of
the set (issue 59, item 4).

    python tools/bench_floor.py DATASET [DATASET ...] [--workers 2] [--json OUT.json]

For each dataset folder, in one run:

- ``decode``: every colour image read as a user would (``cv2.imread`` in colour) and every
  depth image (``cv2.imread`` unchanged, 16-bit), with ``--workers`` processes started and
  chunked as the detection stage's pool; one untimed pass first puts the files in the page
  cache, so both sides read from memory;
- ``calibrate``: ``rgbd-calib calibrate DATASET --out TMP --workers W`` with the defaults (the
  depth stage, report.html, fused.ply and exports included) in a child process, with no
  detection cache: wall time, its stage timings and the peak memory (the largest sum of the
  resident sets of the command and its workers, sampled every 0.1 s).

It prints one row per dataset: the images, the decode, the calibrate, their ratio (the
issue's target: at most 2.0) and the peak (at most 2 GB). The machine's load average is
printed with each row: a shared machine slows both sides, the ratio less.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed import decode_all, end_to_end  # noqa: E402
from toolmain import run_tool  # noqa: E402

from rgbd_calib.core.errors import DatasetError  # noqa: E402
from rgbd_calib.model.dataset import FolderDataset  # noqa: E402


def _decode_any(path: str) -> int:
    """A colour image in colour, a depth image as it is stored (16-bit)."""
    flag = cv2.IMREAD_UNCHANGED if "/depth/" in path else cv2.IMREAD_COLOR
    img = cv2.imread(path, flag)
    if img is None:
        raise RuntimeError(f"{path}: unreadable")
    return int(img.shape[0])


def image_paths(dataset: Path) -> tuple[list[str], list[str]]:
    """Every colour and every depth image of a dataset folder (docs/formats.md)."""
    ds = FolderDataset(dataset)
    colour, depth = [], []
    for cam in ds.cameras:
        for folder, into in (("color", colour), ("depth", depth)):
            d = dataset / cam / folder
            if d.is_dir():
                into += sorted(str(p) for p in d.iterdir() if p.is_file())
    if not colour:
        raise DatasetError(f"{dataset}: no colour images under <camera>/color/")
    return colour, depth


def measure(dataset: Path, workers: int) -> dict[str, Any]:
    colour, depth = image_paths(dataset)
    paths = colour + depth
    decode_all(paths, workers, _decode_any)  # untimed: the page cache
    decode_s = decode_all(paths, workers, _decode_any)
    row = end_to_end(dataset, workers)
    row.update(dataset=str(dataset), colour_images=len(colour), depth_images=len(depth),
               decode_s=decode_s, ratio=row["wall_s"] / decode_s)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("datasets", type=Path, nargs="+", help="dataset folders")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                    help="processes for both sides (default 2)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args(argv)
    for d in args.datasets:
        if not d.is_dir():
            raise NotADirectoryError(f"{d}: not a dataset folder")
    rows = []
    print("| dataset | colour + depth images | decode s | calibrate s | ratio | peak MB | "
          "stages s | load |")
    print("|---|---|---|---|---|---|---|---|")
    for d in args.datasets:
        r = measure(d, args.workers)
        rows.append(r)
        stages = ", ".join(f"{k} {v:.1f}" for k, v in r["stages_s"].items() if v >= 0.5)
        print(f"| {d.name} | {r['colour_images']} + {r['depth_images']} | {r['decode_s']:.1f} | "
              f"{r['wall_s']:.1f} | {r['ratio']:.1f} | {r['peak_tree_rss_mb']:.0f} | {stages} | "
              f"{r['load_before']:.1f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    run_tool(main)
