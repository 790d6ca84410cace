"""Speed benchmark: detection throughput and total calibration time against decoding alone,
end-to-end time and peak memory of the command line.

    python tools/bench_speed.py --data bench_data --md docs/benchmarks.md
    python tools/bench_speed.py --data bench_data --sets race16 --workers 2 --repeats 1 \
        --md docs/benchmarks.md

Sets (rendered once with the synth defaults and cached under ``--data``; an existing render is
reused): ``thesis``, the thesis-size set (4 cameras x 413 frames, 1280x720, thesis-line
layout), and ``race16``, 16 cameras x 1000 frames at 848x480 (race16 layout). For each set and
worker count, repeated ``--repeats`` times:

- ``decode``: ``cv2.imread`` of every colour image (BGR, as a user would read them) in the
  same number of processes, started and chunked like the detection stage's pool (forkserver,
  4 images per task); the floor any pipeline that reads the PNGs has to pay;
- ``calibrate``: ``rgbd_calib.pipelines.calibrate`` with the default config and no detection cache;
  its detection stage gives the throughput. ``--refine none`` (default here) leaves out the
  depth stage (colored ICP), which is not part of the board calibration measured here.

The ratio calibrate / decode is taken within each repetition (same machine state), then the
median over repetitions is reported. One untimed decode pass first puts the PNGs in the page
cache, so both sides read from memory. The machine's load average is recorded with every
run: on a shared machine other processes slow both sides alike, the ratio less so.

Then once per set (``--no-end-to-end`` skips it): the command a user runs,
``rgbd-calib calibrate DATASET --out TMP --workers W`` (defaults: depth stage included,
report.html, fused.ply, exports), in a child process: wall time, its stage timings, and peak
memory: the largest sum of the resident set sizes of the command and all its worker
processes, sampled every 0.1 s (psutil), and the largest single process's peak (``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import psutil
from toolmain import ToolError

from rgbd_calib.core.config import CalibrationConfig
from rgbd_calib.core.parallel import process_context
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.render import SynthParams, synthesize

MD_BEGIN, MD_END = "<!-- bench_speed:begin -->", "<!-- bench_speed:end -->"
STAGE_ORDER = ("detection", "pose", "pose_graph", "bundle", "depth", "joint", "depth_check")


def _stages(rows: list[dict[str, Any]]) -> list[str]:
    found = {k for r in rows for k in r["stages_s"]}
    return [k for k in STAGE_ORDER if k in found] + sorted(found - set(STAGE_ORDER))


@dataclass(frozen=True)
class BenchSet:
    layout: str
    cameras: int
    frames: int
    resolution: tuple[int, int]
    seed: int = 0

    def describe(self, frames: int) -> str:
        w, h = self.resolution
        return f"{self.cameras} cameras x {frames} frames, {w}x{h} PNG, {self.layout} layout"


SETS = {
    "thesis": BenchSet("thesis-line", 4, 413, (1280, 720)),  # the thesis's 413 frame sets
    "race16": BenchSet("race16", 16, 1000, (848, 480)),
}
MEMORY_TARGET_MB = 2048.0  # issue 7: the 16 x 1000 set under 2 GB peak


def _decode(path: str) -> int:
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise RuntimeError(f"{path}: unreadable")
    return int(img.shape[0])


def _decode_ours(path: str) -> int:
    """What a detection worker decodes: the grey image, by the dataset reader's decoder."""
    from rgbd_calib.model.dataset import _decode as read

    return int(read(Path(path), cv2.IMREAD_GRAYSCALE, "image").shape[0])


def decode_all(paths: list[str], workers: int, decode=_decode) -> float:
    """Seconds to decode every image with ``workers`` processes (1: in this process);
    ``decode``: ``cv2.imread`` in colour (the issue's reference), or :func:`_decode_ours`."""
    t0 = time.perf_counter()
    if workers <= 1:
        for p in paths:
            decode(p)
    else:
        with ProcessPoolExecutor(workers, mp_context=process_context()) as ex:
            for _ in ex.map(decode, paths, chunksize=4):
                pass
    return time.perf_counter() - t0


def ensure_dataset(data: Path, spec: BenchSet, frames: int, workers: int) -> Path:
    path = data / f"{spec.layout}-f{frames}-s{spec.seed}"
    if not (path / "ground_truth.yaml").is_file():
        print(f"rendering {path} (once) ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        synthesize(
            path, spec.layout, frames, spec.seed, thesis_board(), SynthParams(), workers=workers
        )
        print(f"  rendered in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return path


class _TreeMemory:
    """Peaks of the summed RSS and of the summed PSS of a process and its descendants, sampled
    on a thread. RSS counts the pages a process shares with others (the libraries every pool
    worker maps, forked from one server) once per process, so its sum overstates what the tree
    holds; PSS splits each shared page among its sharers, so its sum is the tree's physical
    memory (Linux; ``pss`` stays 0 where psutil cannot read it)."""

    def __init__(self, pid: int, period_s: float = 0.1):
        self.root = psutil.Process(pid)
        self.period_s = period_s
        self.peak_bytes = 0
        self.peak_processes = 0
        self.peak_pss_bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        while not self._stop.is_set():
            try:
                procs = [self.root, *self.root.children(recursive=True)]
            except psutil.NoSuchProcess:
                return
            total = pss = 0
            for proc in procs:
                try:
                    info = proc.memory_full_info()
                    total += info.rss
                    pss += getattr(info, "pss", 0)
                except psutil.Error:
                    pass
            if total > self.peak_bytes:
                self.peak_bytes, self.peak_processes = total, len(procs)
            self.peak_pss_bytes = max(self.peak_pss_bytes, pss)
            self._stop.wait(self.period_s)

    def __enter__(self) -> _TreeMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def end_to_end(path: Path, workers: int, keep: Path | None = None) -> dict[str, Any]:
    """``rgbd-calib calibrate`` as a user runs it, in a child process: time and peak memory."""
    out_root = Path(tempfile.mkdtemp(prefix="bench_e2e_")) if keep is None else keep
    out = out_root / "calibration"
    cmd = [
        sys.executable,
        "-c",
        "from rgbd_calib.cli import app; app()",
        "calibrate",
        str(path),
        "--out",
        str(out),
        "--workers",
        str(workers),
    ]
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    with open(out_root / "calibrate.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        with _TreeMemory(proc.pid) as memory:
            code = proc.wait()
    wall_s = time.perf_counter() - t0
    # the largest peak of any one finished descendant (the waited command and its workers)
    maxrss_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    if code != 0:
        tail = (out_root / "calibrate.log").read_text()[-2000:]
        raise ToolError(f"calibrate failed with exit {code}:\n{tail}")
    report = json.loads((out / "report.json").read_text())
    row = {
        "workers": workers,
        "wall_s": wall_s,
        "peak_tree_rss_mb": memory.peak_bytes / 2**20,
        "peak_tree_pss_mb": memory.peak_pss_bytes / 2**20,
        "processes_at_peak": memory.peak_processes,
        "max_single_process_rss_mb": maxrss_mb,
        "stages_s": report.get("timings_s", {}),
        "cameras_calibrated": report["summary"]["n_calibrated"],
        "cameras": report["summary"]["n_cameras"],
        "views_used": report["summary"]["n_views_used"],
        "pairs_accepted": sum(1 for q in report.get("pairs", []) if q.get("accepted")),
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
    }
    if keep is None:
        shutil.rmtree(out_root, ignore_errors=True)
    print(
        f"end to end ({workers} workers): {wall_s:.0f} s, peak {row['peak_tree_rss_mb']:.0f} MB "
        f"RSS over {memory.peak_processes} processes, {row['peak_tree_pss_mb']:.0f} MB PSS",
        file=sys.stderr,
        flush=True,
    )
    return row


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
            ours_s = decode_all(paths, workers, _decode_ours)
            t0 = time.perf_counter()
            result = calibrate(dataset, board, CalibrationConfig(workers=workers, refine=refine))
            calibrate_s = time.perf_counter() - t0
            row = {
                "workers": workers,
                "repeat": rep,
                "images": n,
                "decode_s": decode_s,
                "our_decode_s": ours_s,
                "calibrate_s": calibrate_s,
                "stages_s": dict(result.timings_s),
                "detection_images_per_s": n / result.timings_s["detection"],
                "decode_images_per_s": n / decode_s,
                "ratio": calibrate_s / decode_s,
                "ratio_ours": calibrate_s / ours_s,
                "load_before": load_before,
                "load_after": os.getloadavg()[0],
                "cameras": len(result.extrinsics.cameras),
                "observations": len(result.observations),
            }
            rows.append(row)
            print(
                f"workers {workers} run {rep}: decode {decode_s:.1f} s, calibrate "
                f"{calibrate_s:.1f} s (detection {result.timings_s['detection']:.1f} s), "
                f"ratio {row['ratio']:.2f} (our decode {ours_s:.1f} s: {row['ratio_ours']:.2f}), "
                f"load {load_before:.1f}->{row['load_after']:.1f}",
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
        # runs before the dataset's own decoder was timed have no "our_decode_s"
        "our_decode_s": med(r.get("our_decode_s", math.nan) for r in sel),
        "ratio_ours": med(r.get("ratio_ours", math.nan) for r in sel),
        "load": med(r["load_before"] for r in sel),
        **{f"stage_{k}_s": med(r["stages_s"].get(k, 0.0) for r in sel) for k in stages},
    }


def _num(x: float, digits: int) -> str:
    return "-" if math.isnan(x) else f"{x:.{digits}f}"


def _set_markdown(name: str, block: dict[str, Any]) -> list[str]:
    meta, rows = block["meta"], block["rows"]
    spec = SETS.get(name, SETS["thesis"])
    lines = [f"### {name}: {spec.describe(meta['frames'])}", ""]
    if rows:
        stages = _stages(rows)
        lines += [
            f"{block['images']} colour images; calibration = default config with refine="
            f"{meta.get('refine', 'none')!r} (edge corners, bundle adjustment"
            f"{', no depth stage' if meta.get('refine', 'none') == 'none' else ''}), no "
            f"detection cache; medians of {meta['repeats']} run(s). The ratio is calibrate / "
            "decode within each run (min-max in brackets); calibrate / our decode divides by "
            "the dataset reader's own decode of the same images instead (grey, what a "
            "detection worker does: imagecodecs' libpng since 2026-11-25, '-' for runs "
            "before). Load: the machine's 1-minute load average before the runs (a shared "
            "2-core machine; above 2 other processes were competing).",
            "",
            "| workers | decode (s) | decode (img/s) | detection (img/s) | calibrate total (s) | "
            + " | ".join(f"{s} (s)" for s in stages)
            + " | calibrate / decode | our decode (s) | calibrate / our decode | load |",
            "|---" * (9 + len(stages)) + "|",
        ]
        for w in meta["workers"]:
            s = summary(rows, w)
            if not s["runs"]:
                continue
            lines.append(
                f"| {w} | {s['decode_s']:.1f} | {s['decode_images_per_s']:.0f} | "
                f"{s['detection_images_per_s']:.1f} | {s['calibrate_s']:.1f} | "
                + " | ".join(f"{s[f'stage_{k}_s']:.1f}" for k in stages)
                + f" | {s['ratio']:.2f} ({s['ratio_min']:.2f}-{s['ratio_max']:.2f}) | "
                f"{_num(s['our_decode_s'], 1)} | {_num(s['ratio_ours'], 2)} | {s['load']:.1f} |"
            )
        lines.append("")
    runs = block.get("end_to_end", [])
    if len(runs) > 1:
        med = statistics.median
        walls = ", ".join(f"{e['wall_s']:.0f}" for e in runs)
        peaks = ", ".join(f"{e['peak_tree_rss_mb']:.0f}" for e in runs)
        pss = [e["peak_tree_pss_mb"] for e in runs if e.get("peak_tree_pss_mb")]
        pss_text = (f", **{med(pss):.0f} MB PSS** (runs {', '.join(f'{x:.0f}' for x in pss)})"
                    if len(pss) == len(runs) else "")
        lines += [
            f"End to end, medians of {len(runs)} runs: **{med(e['wall_s'] for e in runs):.0f} s** "
            f"wall (runs {walls} s), **peak memory "
            f"{med(e['peak_tree_rss_mb'] for e in runs):.0f} MB** summed RSS (runs {peaks} MB)"
            f"{pss_text}; each run:",
            "",
        ]
    for e in runs:
        st = e["stages_s"]
        stage_text = ", ".join(f"{k} {v:.1f} s" for k, v in st.items())
        rest_s = e["wall_s"] - sum(st.values())
        verdict = (
            "within" if e["peak_tree_rss_mb"] <= MEMORY_TARGET_MB else "ABOVE"
        ) + f" the {MEMORY_TARGET_MB / 1024:.0f} GB target"
        lines += [
            f"End to end (`rgbd-calib calibrate DATASET --out OUT --workers {e['workers']}`, "
            "defaults: depth stage, report, fused cloud, exports): "
            f"**{e['wall_s']:.0f} s** wall ({stage_text}; the other {rest_s:.0f} s: "
            "start-up, the dataset index, writing the outputs, fused cloud and report), "
            f"**peak memory {e['peak_tree_rss_mb']:.0f} MB** RSS summed over "
            f"{e['processes_at_peak']} processes"
            + (f", {e['peak_tree_pss_mb']:.0f} MB PSS" if e.get("peak_tree_pss_mb") else "")
            + f" ({verdict}; largest single process "
            f"{e['max_single_process_rss_mb']:.0f} MB); {e['cameras_calibrated']}/"
            f"{e['cameras']} cameras calibrated from {e['views_used']} board views, "
            f"{e['pairs_accepted']} depth pairs accepted; load "
            f"{e['load_before']:.1f} -> {e['load_after']:.1f}.",
            "",
        ]
    return lines


def markdown(payload: dict[str, Any]) -> str:
    meta = payload["meta"]
    lines = [
        f"Generated by `{meta['command']}` on {meta['machine']} ({meta['date']}).",
        "",
    ]
    for name, block in payload["sets"].items():
        lines += _set_markdown(name, block)
    return "\n".join(lines).rstrip("\n") + "\n"


def _upgrade(payload: dict[str, Any]) -> dict[str, Any]:
    """A JSON written before the sets existed: one thesis-line block."""
    if "sets" in payload:
        return payload
    meta = dict(payload["meta"])
    return {"meta": meta, "sets": {"thesis": {**payload, "meta": meta}}}


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


def _merge(path: Path, payload: dict[str, Any]) -> dict[str, Any]:
    """``payload`` merged into the results already in ``path``: the sets run now replace
    theirs, the others are kept (so the sets can be run one command at a time)."""
    try:
        earlier = _upgrade(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError):
        return payload
    kept = {k: v for k, v in earlier["sets"].items() if k not in payload["sets"]}
    if not kept:
        return payload
    meta = dict(payload["meta"])
    meta["command"] = f"{earlier['meta']['command']}` then `{meta['command']}"
    return {"meta": meta, "sets": {**kept, **payload["sets"]}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--data", type=Path, default=Path("bench_data"), help="folder of the rendered sets (reused)"
    )
    p.add_argument("--sets", nargs="+", default=["thesis"], choices=list(SETS))
    p.add_argument(
        "--frames", type=int, default=None, help="frames per set (default: the set's own)"
    )
    p.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    p.add_argument("--repeats", type=int, default=3, help="calibrate/decode runs per worker count")
    p.add_argument(
        "--refine",
        default="none",
        choices=["none", "auto", "colored-icp", "geometric"],
        help="depth stage of the calibrate/decode runs (default: none, board only)",
    )
    p.add_argument(
        "--no-end-to-end", action="store_true", help="skip the command-line run with memory"
    )
    p.add_argument(
        "--end-to-end-repeats", type=int, default=1,
        help="command-line runs (the markdown gives their medians when more than one)",
    )
    p.add_argument(
        "--keep", type=Path, default=None,
        help="keep the (first) end-to-end run's outputs under this folder",
    )
    p.add_argument(
        "--json",
        type=Path,
        default=Path("docs/speed.json"),
        help="results; sets already in it that were not run now are kept",
    )
    p.add_argument(
        "--md",
        type=Path,
        default=None,
        help="markdown file whose Speed block is replaced (e.g. docs/benchmarks.md)",
    )
    p.add_argument(
        "--from-json",
        type=Path,
        default=None,
        help="re-make the tables from this JSON; run nothing",
    )
    args = p.parse_args(argv)
    if args.from_json:
        payload = _upgrade(json.loads(args.from_json.read_text()))
    else:
        payload = {
            "meta": {
                "command": "python tools/bench_speed.py "
                + " ".join(argv if argv is not None else sys.argv[1:]),
                "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
                f"{psutil.virtual_memory().total / 2**30:.0f} GiB, "
                f"Python {platform.python_version()}, OpenCV {cv2.__version__}",
                "date": time.strftime("%Y-%m-%d"),
            },
            "sets": {},
        }
        for name in args.sets:
            spec = SETS[name]
            frames = args.frames or spec.frames
            path = ensure_dataset(args.data, spec, frames, max(args.workers))
            block = (
                run(path, args.workers, args.repeats, args.refine)
                if args.repeats
                else {"images": None, "rows": []}
            )
            block["meta"] = {
                "frames": frames,
                "workers": args.workers,
                "repeats": args.repeats,
                "dataset": str(path),
                "refine": args.refine,
            }
            if not args.no_end_to_end:
                keep = args.keep / name if args.keep else None
                if keep:
                    keep.mkdir(parents=True, exist_ok=True)
                block["end_to_end"] = [
                    end_to_end(path, max(args.workers), keep if rep == 0 else None)
                    for rep in range(args.end_to_end_repeats)
                ]
            payload["sets"][name] = block
        payload = _merge(args.json, payload)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(payload, indent=1))
    body = markdown(payload)
    print(body)
    if args.md:
        write_markdown(args.md, body)
    return 0


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
