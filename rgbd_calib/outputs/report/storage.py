"""How a report is stored: ``report.json``, and for a large rig its per-view detail in a
compact side file (docs/report_schema.md, "Large rigs: views in a side file").

Up to :data:`VIEWS_INLINE_MAX` views, ``report.json`` holds ``views`` inline, exactly as
before. Above it, ``views`` moves to :data:`VIEWS_FILE`, gzip-compressed NDJSON (one view
object per line, the same keys and values as ``views[]``), and ``report.json`` holds the
pointer ``views_file`` in its place; 30 000 views are then ~1 MB of report.json plus ~5 MB of
side file instead of ~23 MB of report.json (docs/benchmarks.md). NDJSON rather than Parquet:
the standard library writes and reads it (pyarrow is ~170 MB installed), ``zcat | jq``,
pandas and DuckDB read it as it is, and it is only ~20 % larger.

:func:`load_report` gives the report with ``views`` inline either way, the form every report
module works on. Numpy-free, like the schema.
"""

from __future__ import annotations

import gzip
import hashlib
import json
from pathlib import Path
from typing import Any

from .schema import ReportError, dump_report

VIEWS_INLINE_MAX = 2000  # views kept inline in report.json; more go to VIEWS_FILE
VIEWS_FILE = "report_views.ndjson.gz"
VIEWS_FORMAT = "ndjson.gz"


def split_report(report: dict[str, Any], views_inline_max: int = VIEWS_INLINE_MAX,
                 ) -> tuple[dict[str, Any], bytes | None]:
    """``report`` (``views`` inline) as stored: itself and no side file up to
    ``views_inline_max`` views; above, a copy whose ``views`` is replaced, in place, by the
    ``views_file`` pointer, and the side file's bytes (deterministic: a rebuild reproduces
    them)."""
    views = report["views"]
    if len(views) <= views_inline_max:
        return report, None
    text = "".join(json.dumps(v, allow_nan=False, separators=(",", ":")) + "\n"
                   for v in views).encode()
    pointer = {"path": VIEWS_FILE, "format": VIEWS_FORMAT, "count": len(views),
               "sha256": hashlib.sha256(text).hexdigest()}
    stored = {("views_file" if k == "views" else k): (pointer if k == "views" else v)
              for k, v in report.items()}
    return stored, gzip.compress(text, compresslevel=6, mtime=0)


def join_views(stored: dict[str, Any], side: bytes, where: Path) -> dict[str, Any]:
    """The stored report with the views of its side file (``side``, the file's bytes) back
    inline in place of ``views_file``; a side file that does not match the pointer (another
    run's, truncated) is a :class:`ReportError` naming ``where``."""
    pointer = stored["views_file"]
    try:
        text = gzip.decompress(side)
    except (OSError, EOFError) as exc:
        raise ReportError(f"{where}: not a gzip file ({exc}); re-run calibrate") from None
    if hashlib.sha256(text).hexdigest() != pointer.get("sha256"):
        raise ReportError(f"{where}: does not match the report.json beside it (another run's, "
                          "or changed); re-run calibrate")
    views = [json.loads(line) for line in text.decode().splitlines() if line]
    return {("views" if k == "views_file" else k): (views if k == "views_file" else v)
            for k, v in stored.items()}


def write_report_json(report: dict[str, Any], folder: Path,
                      views_inline_max: int = VIEWS_INLINE_MAX) -> list[Path]:
    """Write ``report`` (``views`` inline) into ``folder`` as ``report.json`` and, above
    ``views_inline_max`` views, :data:`VIEWS_FILE`; the files written. Not atomic by itself:
    write into a staging folder (:func:`rgbd_calib.outputs.writer.staged`) or use
    :func:`rgbd_calib.core.yamlio.atomic_write_text` semantics through the caller."""
    from ...core.yamlio import atomic_write_bytes, atomic_write_text

    folder = Path(folder)
    stored, side = split_report(report, views_inline_max)
    written = []
    if side is not None:  # the side file first: report.json never points at a missing one
        atomic_write_bytes(folder / VIEWS_FILE, side)
        written.append(folder / VIEWS_FILE)
    atomic_write_text(folder / "report.json", dump_report(stored))
    written.append(folder / "report.json")
    if side is None:
        (folder / VIEWS_FILE).unlink(missing_ok=True)  # an older, larger run's
    return written


def load_report(path: Path) -> dict[str, Any]:
    """``report.json`` at ``path`` with ``views`` inline, read from its side file when it
    has one (:class:`ReportError` when that is missing or does not match)."""
    path = Path(path)
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ReportError(f"{path}: not valid JSON ({exc}); re-run calibrate") from None
    if not isinstance(report, dict) or not isinstance(report.get("views_file"), dict):
        return report
    name = str(report["views_file"].get("path", VIEWS_FILE))
    side = path.parent / name
    if Path(name).name != name or not side.is_file():
        raise ReportError(f"{side}: missing; report.json keeps its per-view detail there: "
                          "copy the calibration folder whole, or re-run calibrate")
    return join_views(report, side.read_bytes(), side)
