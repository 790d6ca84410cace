"""The conversion cache: recordings converted once into a folder that calibrate reads.

The folder holds a marker file with the sources' sizes and modification times and the
conversion's report; a changed recording is converted again.
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..core.errors import ConfigError, DatasetError
from ..core.progress import Progress
from ..core.yamlio import atomic_write_text
from ..model.dataset import FolderDataset
from .conversion import ConversionReport, check_source, convert, is_recording
from .staging import sanitize_name
from .video import is_video

CACHE_MARKER = ".rgbd-calib-source.json"
CACHE_FORM = 2  # the folder form a conversion in the cache has (2: timestamps.csv)


def _source_stamp(sources: Sequence[Path], names, sync_tolerance_ms) -> dict[str, Any]:
    entries = []
    for src in sources:
        files = sorted(p for p in src.rglob("*") if p.is_file()) if src.is_dir() else [src]
        stats = [p.stat() for p in files]
        entries.append(
            {
                "path": str(src.resolve()),
                "size": sum(s.st_size for s in stats),
                "mtime_ns": max((s.st_mtime_ns for s in stats), default=0),
            }
        )
    # form 2: with <camera>/timestamps.csv (an older conversion is made again, once)
    return {"sources": entries, "names": list(names or []), "sync_tolerance_ms": sync_tolerance_ms,
            "form": CACHE_FORM}


def convert_to_cache(
    source: Path | Sequence[Path],
    cache_dir: Path,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
) -> Path:
    """Folder form of a recording under ``cache_dir``, converted once.

    A second call returns the earlier conversion while every source's size and modification
    time are unchanged; otherwise the cached folder is converted again. The conversion's
    report is kept beside it (:func:`cached_report`)."""
    sources = [Path(source)] if isinstance(source, (str, Path)) else [Path(s) for s in source]
    for src in sources:
        check_source(src)
    stamp = _source_stamp(sources, names, sync_tolerance_ms)
    key = hashlib.sha1(
        json.dumps([e["path"] for e in stamp["sources"]] + stamp["names"]).encode()
    ).hexdigest()[:12]
    folder = Path(cache_dir) / f"{sanitize_name(sources[0].stem)}-{key}"
    if _read_marker(folder).get("source") == stamp:
        return folder
    if folder.exists():
        shutil.rmtree(folder)
    report = convert(sources, folder, names, sync_tolerance_ms, progress)
    atomic_write_text(
        folder / CACHE_MARKER,
        json.dumps({"source": stamp, "report": report.to_dict()}, indent=1),
    )
    return folder


def _read_marker(folder: Path) -> dict[str, Any]:
    try:
        data = json.loads((Path(folder) / CACHE_MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def cached_report(folder: Path) -> ConversionReport | None:
    """The report of the conversion that made ``folder`` in a cache; None for any other
    folder (a dataset folder, say)."""
    data = _read_marker(folder).get("report")
    try:
        return ConversionReport.from_dict(data) if isinstance(data, dict) else None
    except (KeyError, TypeError, ValueError):
        return None


def dataset_folder(
    sources: Sequence[str | os.PathLike],
    cache_dir: str | os.PathLike | None,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
) -> Path:
    """The folder form to calibrate from: a dataset folder as it is, or recordings converted
    once into ``cache_dir`` (see :func:`convert_to_cache`; converted again when a recording
    changes).

    One source that is not a recording (no .bag/.db3/.mcap suffix, not a ROS 2 bag folder) is
    taken as a dataset folder: :class:`FolderDataset` then names what is wrong with it.
    Videos, or a folder of videos or recordings without a dataset in it, are refused with the
    ``rgbd-calib convert`` command that makes one. ``names`` and ``sync_tolerance_ms`` apply
    to recordings only; without ``cache_dir`` recordings are refused (convert them first)."""
    sources = [Path(s) for s in sources]
    if not sources:
        raise ConfigError("give a dataset folder or at least one recording")
    if videos := [s for s in sources if s.is_file() and is_video(s)]:
        raise DatasetError(
            f"{videos[0]}: a video; calibrate, check and refine read a dataset folder or "
            f"RealSense/ROS recordings: convert the videos first with `rgbd-calib convert "
            f"{_shell_list(videos)} --out DATASET`, then give DATASET")
    single = sources[0]
    if len(sources) == 1 and not is_recording(single):
        if names or sync_tolerance_ms is not None:
            raise ConfigError(
                f"{single}: --names and --sync-tolerance-ms apply to recordings, not to a "
                "dataset folder; drop them (camera names come from its rig.yaml)"
            )
        refuse_unconverted(single)
        return single
    for src in sources:
        if src.is_dir() and not is_recording(src):
            raise DatasetError(
                f"{src}: a dataset folder cannot be mixed with recordings; pass either one "
                "dataset folder or only recordings"
            )
    if cache_dir is None:
        raise ConfigError(f"{sources[0]}: a recording; convert it first with `rgbd-calib "
                          f"convert {_shell_list(sources)} --out DATASET` (or "
                          "rgbd_calib.convert) and give DATASET")
    return convert_to_cache(sources, Path(cache_dir), names, sync_tolerance_ms, progress)


def open_dataset(dataset: FolderDataset | str | os.PathLike) -> FolderDataset:
    """``dataset`` as it is, or the dataset folder at that path (a folder of videos or
    recordings is refused with the command that converts it: :func:`refuse_unconverted`)."""
    if isinstance(dataset, FolderDataset):
        return dataset
    return FolderDataset(dataset_folder([dataset], None))


def refuse_unconverted(folder: Path) -> None:
    """A folder without a dataset (no rig.yaml) that holds videos or recordings: one line
    naming it, and the ``rgbd-calib convert`` command that makes a dataset of them."""
    if not folder.is_dir() or (folder / "rig.yaml").exists():
        return
    entries = sorted(folder.iterdir())
    videos = [p for p in entries if p.is_file() and is_video(p)]
    recordings = [p for p in entries if is_recording(p) and not p.name.startswith(".")]
    found = videos or recordings
    if not found:
        return
    kind = "videos" if videos else "recordings"
    shown = ", ".join(p.name for p in found[:3]) + (", ..." if len(found) > 3 else "")
    suffixes = {p.suffix.lower() for p in found}
    given = (shlex.quote(str(folder)) + "/*" + found[0].suffix
             if len(suffixes) == 1 and found[0].suffix and not any(p.is_dir() for p in found)
             else _shell_list(found))
    instead = ("" if videos else
               f" (or pass the recordings themselves instead of the folder: {given})")
    raise DatasetError(
        f"{folder}: holds {kind} ({shown}), not a dataset folder; convert them first with "
        f"`rgbd-calib convert {given} --out DATASET`, then give DATASET{instead}")


def _shell_list(paths: Sequence[Path]) -> str:
    return " ".join(shlex.quote(str(p)) for p in paths)
