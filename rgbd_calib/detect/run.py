"""Markers in every colour image of a dataset: :func:`detect_dataset`, in a process pool (or on a
Dask cluster), reusing a JSON cache keyed by the board, the detection settings and each image's
file and lens.

The pool runs :func:`rgbd_calib.detect.markers.init_detector` and
:func:`~rgbd_calib.detect.markers.detect_job`; this module imports no solver, so neither does a
worker that loads it.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

from ..core.camera import CameraIntrinsics
from ..core.config import DetectionConfig
from ..core.parallel import executor as make_executor
from ..core.progress import Tick
from ..core.yamlio import atomic_write_text
from ..model.board import Board
from ..model.dataset import FolderDataset
from .markers import MarkerDetections, detect_job, init_detector

# 2: colour PNGs read as grey by OpenCV's weights (libpng's own grey was 1 DN off on half the
# pixels), so detections of the same file differ slightly from a version-1 cache's
CACHE_VERSION = 2
CACHE_SAVE_EVERY_S = 30.0  # an interrupted detection loses at most about this much work


def _fingerprint(board: Board, config: DetectionConfig) -> str:
    text = json.dumps(
        [board.to_dict(), board.corners.tolist(), config.flat_dump(), CACHE_VERSION],
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _lens_key(intrinsics: CameraIntrinsics) -> str:
    """What of a camera's model the edge fit depends on: nothing for a pinhole camera (its
    marker edges are straight), the whole model when the lens distorts (the fit bends the
    edges with it)."""
    if not intrinsics.has_distortion:
        return ""
    text = json.dumps(intrinsics.to_dict(), sort_keys=True, default=float)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _file_key(path: Path) -> str:
    st = path.stat()
    return f"{st.st_size}:{st.st_mtime_ns}"


def detect_dataset(
    dataset: FolderDataset,
    board: Board,
    config: DetectionConfig,
    cache_path: Path | None = None,
    workers: int | None = None,
    progress: Tick | None = None,
    scheduler: str | None = None,
) -> dict[tuple[str, str], MarkerDetections]:
    """Detect markers in every colour image, in a process pool (or on the Dask cluster of
    ``scheduler``, :func:`rgbd_calib.core.parallel.executor`), reusing a cache.

    The cache (JSON) is keyed by the board and detection settings and, per image, by file
    size and modification time; it is saved every :data:`CACHE_SAVE_EVERY_S` seconds (and
    at least 500 images apart) so an interrupted run resumes where it stopped. Each image's
    entry is serialised once, to a JSON string: saving the whole cache every 500 images
    cost a 16 x 1000 set ~20 s of the main process's CPU (a 26 MB JSON, 32 times), and
    keeping the entries as Python objects would cost memory."""
    fingerprint = _fingerprint(board, config)
    lens = {c: _lens_key(i) for c, i in dataset.rig.cameras.items()}
    cached: dict[str, dict] = {}
    if cache_path is not None and cache_path.is_file():
        try:
            data = json.loads(cache_path.read_text())
            if data.get("fingerprint") == fingerprint:
                cached = data["images"]
        except (ValueError, KeyError):
            cached = {}  # a corrupt cache is only a cache: detect again
    results: dict[tuple[str, str], MarkerDetections] = {}
    entries: dict[str, str] = {}  # the cache's images: key -> its entry as JSON text
    jobs = []
    for fs in dataset.frame_sets():
        for cam, path in fs.color.items():
            key = f"{cam}/{fs.frame}"
            entry = cached.get(key)
            intr = dataset.rig.cameras[cam]
            if (entry is not None and entry.get("file") == _file_key(path)
                    and entry.get("lens", "") == lens[cam]):
                results[(cam, fs.frame)] = MarkerDetections.from_dict(entry["det"])
                if cache_path is not None:
                    entries[key] = json.dumps(entry)
            else:
                job = (cam, fs.frame, str(path), intr.width, intr.height)
                jobs.append(job + (intr,) if intr.has_distortion else job)
    if progress:
        progress(len(results))

    def keep(cam: str, frame: str, det: dict) -> None:
        results[(cam, frame)] = MarkerDetections.from_dict(det)
        if cache_path is not None:
            entry = {"file": _file_key(dataset.color_path(cam, frame)), "det": det}
            if lens[cam]:
                entry["lens"] = lens[cam]
            entries[f"{cam}/{frame}"] = json.dumps(entry)

    def save() -> None:
        if cache_path is not None:
            images = ", ".join(f"{json.dumps(k)}: {v}" for k, v in entries.items())
            text = f'{{"fingerprint": {json.dumps(fingerprint)}, "images": {{{images}}}}}'
            atomic_write_text(cache_path, text)

    workers = workers or os.cpu_count() or 1
    done_since_save, saved_at = 0, time.monotonic()
    executor = None
    if scheduler and jobs:
        # connected before the try: a scheduler that does not answer writes no cache
        executor = make_executor(scheduler=scheduler, initializer=init_detector,
                                 initargs=(board, config))
    elif workers > 1 and len(jobs) >= 8:
        executor = make_executor(workers, initializer=init_detector, initargs=(board, config))
    try:
        if executor is None:
            init_detector(board, config, threads=-1)
            iterator = map(detect_job, jobs)
        else:
            iterator = executor.map(detect_job, jobs, chunksize=4)
        for cam, frame, det in iterator:
            keep(cam, frame, det)
            done_since_save += 1
            if progress:
                progress(1)
            if done_since_save >= 500 and time.monotonic() - saved_at >= CACHE_SAVE_EVERY_S:
                save()
                done_since_save, saved_at = 0, time.monotonic()
    finally:
        if jobs:
            save()
        if executor is not None:
            executor.shutdown(cancel_futures=True)
    return results
