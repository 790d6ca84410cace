"""The command line's output: rich progress bars, live displays and tables.

The library reports through :mod:`rgbd_calib.core.progress` and typed results and never
imports rich; this module turns those into terminal output for :mod:`rgbd_calib.cli.commands`:
progress bars (drawn only on a terminal, stderr), the summary of a calibration, the check's
and the demo's tables, the verdict (tables and notes are printed either way).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import statistics
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape

from ..core.depth_model import TERMS
from ..core.progress import Progress

if TYPE_CHECKING:
    from ..solve.edge_offset import EdgeOffset

console = Console(stderr=True)


def _table_console() -> Console:
    """stdout for the extrinsics table: the terminal's width, or in a file or pipe
    :data:`CONSOLE_WIDTH` columns (at rich's default 80 the demo's table cut its numbers to
    '0.53…'),
    unless ``COLUMNS`` says otherwise."""
    out = Console()
    if not out.is_terminal and "COLUMNS" not in os.environ:
        out = Console(width=CONSOLE_WIDTH)
    return out


# --------------------------------------------------------------------------- progress
def progress_bar():
    """A rich bar with counts and times, shown only when stderr is a terminal."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.progress import Progress as RichProgress

    return RichProgress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not sys.stderr.isatty(),
    )


# every line PlainProgress writes (a log reader or a test can tell them from results and errors)
PROGRESS_LINE = re.compile(r"^(?!error:)[^:\n]+: (started$|\d+/\d+ |\d+ done, )")


class PlainProgress:
    """The progress protocol as plain lines, for a log file or a pipe (CI, nohup, ssh):
    ``stage: done/total (pct), rate/s, ETA`` when a stage starts, at most every
    ``interval_s`` seconds while it runs, and ``stage: total/total done in T s`` when it ends
    (``total`` None: counts and rate only)."""

    def __init__(self, write=None, interval_s: float = 10.0, clock=None) -> None:
        import time

        self.write = write or (lambda line: print(line, file=sys.stderr, flush=True))
        self.interval_s = interval_s
        self.clock = clock or time.monotonic

    def __call__(self, label: str, total: int | None, done: int = 0):
        start_done, t0 = done, self.clock()
        state = {"done": done, "last": t0}

        def line(now: float) -> str:
            n = state["done"]
            elapsed = now - t0
            rate = (n - start_done) / elapsed if elapsed > 0 else 0.0
            if total is None:
                return f"{label}: {n} done, {rate:.1f}/s, {elapsed:.0f} s"
            if n >= total:
                return f"{label}: {n}/{total} done in {elapsed:.1f} s"
            eta = f"ETA {(total - n) / rate:.0f} s" if rate > 0 else "ETA unknown"
            pct = 100.0 * n / total if total else 100.0
            return f"{label}: {n}/{total} ({pct:.0f}%), {rate:.1f}/s, {eta}"

        if total is None:
            self.write(f"{label}: started")
        elif done >= total:
            self.write(f"{label}: {done}/{total} (nothing to do)" if not total
                       else f"{label}: {done}/{total} already done (cached)")
        else:
            self.write(f"{label}: {done}/{total} started")

        def tick(n: int = 1) -> None:
            before = state["done"]
            state["done"] += n
            now = self.clock()
            finished = total is not None and before < total <= state["done"]
            if finished or now - state["last"] >= self.interval_s:
                state["last"] = now
                self.write(line(now))

        return tick


@contextlib.contextmanager
def stage_progress() -> Iterator[Progress]:
    """The library's progress protocol, ``progress(label, total, done) -> tick(n=1)``, as one
    rich bar per stage on a terminal (``total`` None: a bar without an end), as plain
    :class:`PlainProgress` lines otherwise."""
    if not sys.stderr.isatty():
        yield PlainProgress()
        return
    with progress_bar() as bar:

        def progress(label: str, total: int | None, done: int = 0):
            task = bar.add_task(label, total=total, completed=done)
            return lambda n=1: bar.advance(task, n)

        yield progress


# --------------------------------------------------------------------------- verdict
VERDICT_MEANING = {
    "good": "no warning; the extrinsics are ready to use",
    "check": "usable, but look at the warnings below first",
    "poor": "do not use these extrinsics as they are; see the errors below",
}
VERDICT_STYLE = {"good": "bold green", "check": "bold yellow", "poor": "bold red"}
SEVERITY_STYLE = {"error": "red", "warning": "yellow", "info": "cyan"}
# findings printed on the console; report.json and report.html hold every one
CONSOLE_FINDINGS = 3
CONSOLE_WIDTH = 100  # the terminal the console is written for: each finding or note in at
CONSOLE_ROWS = 2  # most this many of its rows; report.html / report.json hold the rest


def shortened(text: str, rows: int = CONSOLE_ROWS, width: int = CONSOLE_WIDTH) -> str:
    """``text`` in at most ``rows`` rows of ``width`` characters: whole when it fits, else
    cut at a word with an ellipsis (the full text is in report.html / report.json)."""
    text = " ".join(text.split())
    limit = rows * width - 2
    if len(text) <= limit:
        return text
    cut = text.rfind(" ", 0, limit - 1)
    return text[:cut if cut > limit // 2 else limit - 1].rstrip(" ,;:") + " …"


def verdict_lines(report: dict, limit: int = CONSOLE_FINDINGS) -> list[tuple[str, str]]:
    """``(style, text)`` lines ending a calibration's console output: the verdict, the
    ``limit`` actionable findings of ``report.json`` that matter most, each its action and
    why in at most :data:`CONSOLE_ROWS` rows (errors, warnings, then advice; a finding with
    nothing to do is not listed), then how many more the report holds."""
    from ..outputs.report.findings_base import ranked_actionable

    verdict = report.get("summary", {}).get("verdict", "check")
    lines = [(VERDICT_STYLE.get(verdict, "bold"),
              f"verdict: {verdict.upper()}: {VERDICT_MEANING.get(verdict, '')}")]
    found = report.get("warnings", [])
    shown = ranked_actionable(found)[:limit]
    for w in shown:  # the action first, then why; at most two rows each
        cams = f" [{', '.join(w['cameras'])}]" if w.get("cameras") else ""
        text = shortened(f"{w['severity']}: {w['code']}{cams}: {w['advice']} (why: "
                         f"{w['message']})")
        lines.append((SEVERITY_STYLE.get(w["severity"], ""), text))
    if rest := len(found) - len(shown):
        lines.append(("", f"+ {rest} more finding{'s' if rest > 1 else ''} in report.html / "
                          "report.json"))
    return lines


def print_verdict(out: Path) -> None:
    """Print where the results are, then the verdict and warnings of ``out/report.json``, and
    last the path of ``report.html``."""
    import json

    report = json.loads((Path(out) / "report.json").read_text())
    extras = [n for n in ("fused.ply", "rig_refined.yaml", "board_refined.yaml")
              if (Path(out) / n).exists()]
    files = ", ".join(["extrinsics.yaml", "report.json", *extras, "exports/"])
    console.print(f"results in {out}/ ({files})", highlight=False, soft_wrap=True)
    for style, text in verdict_lines(report):
        head, _, rest = text.partition(":")
        console.print(f"[{style}]{escape(head)}:[/]{escape(rest)}" if style else escape(text),
                      highlight=False, soft_wrap=True)
    console.print(f"report: {Path(out) / 'report.html'}", highlight=False, soft_wrap=True)


# --------------------------------------------------------------------------- results
def warn_line(message: str) -> None:
    console.print(f"[yellow]warning[/]: {message}", highlight=False, soft_wrap=True)


def _fixed(value: float, digits: int) -> str:
    """``value`` with ``digits`` decimals, never ``-0.000`` (a rounding, not a sign)."""
    return f"{round(float(value), digits) + 0.0:.{digits}f}"


def fused_line(agreement, far: dict | None = None) -> str | None:
    """'fused cloud: cameras agree within 0.6 mm in their 9 overlaps (worst pair bias; 4.1 mm
    before the depth models), p90 7.2 mm where the depth noise predicts 6.8' from the depth
    stage's :class:`~rgbd_calib.depth.agreement.FusedAgreement` (None: no pairs), then the
    cameras whose cloud beyond the board's depths is known to worse than a centimetre
    (``far``: camera -> :class:`~rgbd_calib.depth.depth_model_fit.BeyondBoard`; the warning
    ``depth_extrapolated``), which the overlaps cannot see when cameras err alike; None when
    there is neither."""
    from ..outputs.report.findings_depth import is_far
    from ..outputs.report.schema import FAR_WARN_SIGMA_MM

    pairs = agreement.pairs if agreement is not None else []
    uncertain = sorted(((c, b) for c, b in (far or {}).items()
                        if is_far(b.fraction, b.sigma_mm, FAR_WARN_SIGMA_MM)),
                       key=lambda cb: -cb[1].sigma_mm)
    if not pairs and not uncertain:
        return None
    parts = []
    if pairs:
        worst, before = agreement.worst_bias_mm(), agreement.worst_bias_mm(before=True)
        p90 = statistics.median(p.after.p90_mm for p in pairs)
        noise = statistics.median(p.noise_p90_mm for p in pairs)
        text = (f"cameras agree within {worst:.1f} mm in their {len(pairs)} overlaps "
                "(worst pair bias")
        if any(p.before is not None for p in pairs):
            text += f"; {before:.1f} mm before the depth models"
        text += f"), p90 {p90:.1f} mm where the depth noise predicts {noise:.1f}"
        off = agreement.off_cameras + [f"{a} or {b}" for a, b in agreement.ambiguous]
        parts.append(text + (f"; off beyond the noise: {', '.join(off)}" if off else ""))
    if uncertain:
        parts.append("[yellow]beyond the board known only to[/] " + ", ".join(
            f"+-{b.sigma_mm:.0f} mm ({c} at {b.cloud_p90_m:.1f} m)" for c, b in uncertain))
    return "fused cloud: " + "; ".join(parts)


def depth_registration_line(depth: Any) -> str | None:
    """What the depth pairs did to the extrinsics, one line (markup), from the depth stage's
    :class:`~rgbd_calib.depth.stage.DepthRefinement`: confirmed the board result, not used
    and why, not needed, or used with their variance factor; None when nothing was
    registered."""
    from ..outputs.report.findings import confirming_pairs

    pairs = depth.pairs
    agree = len(confirming_pairs([p.to_dict() for p in pairs]))
    if depth.fallback is not None and agree:
        return (f"depth registration: {agree} of {len(pairs)} camera pairs agree with the "
                "board result within their own uncertainty; nothing to correct, the "
                "extrinsics are the board result")
    if depth.fallback is not None:
        return (f"[yellow]depth refinement not used[/]: {escape(depth.fallback)}; the "
                "extrinsics are the board result")
    if depth.note is not None:
        return f"depth registration: {escape(depth.note)}"
    if depth.used:
        factor, bias = depth.pair_variance_factor, depth.pair_bias_sigma
        plus = (f", plus a {bias[0]:g} mm / {bias[1]:g} deg bias" if bias is not None
                and bias[0] > 0 and bias[1] > 0 else "")
        return (f"depth registration: {len(depth.relative_poses)} of {len(pairs)} camera "
                "pairs used with the board's corners for the weakly held cameras"
                + (f" (their covariance x{factor:.2f}: variance factor from their residuals, "
                   f"at least depth.uncertainty.pair_variance_floor{plus})"
                   if factor is not None else ""))
    return None


def depth_model_line(fits: dict, unmodelled: dict | None = None) -> str:
    """'depth model: every term for left0, left1, right0 offset, 5 identity, none for right3;
    board-plane bias within 0.4 mm after the model (3.1 mm before), noise 5.2 mm' from the
    depth stage's fits and the cameras with depth it had no model for. A camera that kept the
    ladder's terms for want of views (``depth.model_fit.model_terms: auto``, ``too_few_views``)
    says so, and one whose model predicted held-out board views no better
    (``held_out.rejected``)."""
    from ..depth.depth_model_fit import EVERY_TERM_MIN_VIEWS  # open3d: not at CLI start
    every = [c for c, f in sorted(fits.items()) if f.model.terms == tuple(TERMS)]
    named = ([f"every term for {', '.join(every)}"] if every else []) + [
        f"{c} {'+'.join(f.model.terms)}" + (
            f" ({f.n_views} board views, {EVERY_TERM_MIN_VIEWS} free every term)"
            if f.too_few_views else "")
        for c, f in sorted(fits.items()) if f.model.terms and c not in every]
    rejected = sorted(c for c, f in fits.items() if f.held_out is not None and f.held_out.rejected)
    clean = sum(1 for c, f in fits.items() if not f.model.terms and c not in rejected)
    parts = named + ([f"{clean} identity"] if clean else []) + (
        [f"raw depth for {', '.join(rejected)} (its model predicted held-out board views no "
         "better)"] if rejected else [])
    if unmodelled:
        parts.append(f"none for {', '.join(sorted(unmodelled))} (uncorrected)")
    bands = [b for f in fits.values() for b in f.bands]
    if not bands:
        return "depth model: " + ", ".join(parts)
    before = max(abs(b[3]) for b in bands)
    after = max(abs(b[4]) for b in bands)
    noise = statistics.median(b[7] for b in bands)
    return (f"depth model: {', '.join(parts)}; depth on the board within {after:.1f} mm "
            f"of its true plane after the model ({before:.1f} mm before; median per distance "
            f"band, single-pixel noise {noise:.1f} mm); depth_model.yaml")


def print_summary(result, out: Path, verdict: bool = True, truth=None) -> None:
    """The extrinsics table (one row a camera; with ``truth``, a synthetic rig's ground truth,
    each camera's error against it too) and notes of at most two rows each, then
    (``verdict``) the verdict, the findings and where the results are."""
    from rich import box
    from rich.table import Table

    from ..core.geometry import invert_transform, transform_error
    from ..outputs.report.build import board_refined_entry
    from ..outputs.report.findings import (
        board_scale_sentence,
        common_depth_scale,
        glue_sentence,
        time_sentence,
    )

    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, collapse_padding=True)
    columns = ["camera", "views", "x m", "y m", "z m", "sigma deg", "sigma mm"]
    if truth is not None:  # a synthetic rig: its errors against the truth
        columns += ["error deg", "error mm", "err/sigma"]
    for col in columns:
        table.add_column(col, justify="right", no_wrap=True)
    views = {}
    for o in result.observations:
        views[o.camera] = views.get(o.camera, 0) + 1
    for name, cam in result.extrinsics.cameras.items():
        t = cam.T_ref_cam[:3, 3]
        ref = " (ref)" if name == result.extrinsics.reference else ""  # the frame's origin
        row = [name + ref, str(views.get(name, 0)), _fixed(t[0], 4), _fixed(t[1], 4),
               _fixed(t[2], 4), _fixed(cam.sigma_rotation_deg, 4),
               _fixed(cam.sigma_translation_mm, 3)]
        if truth is not None:
            deg, mm = transform_error(cam.T_ref_cam, invert_transform(
                truth.T_ref_cam[result.extrinsics.reference]) @ truth.T_ref_cam[name])
            ratio = (max(mm / cam.sigma_translation_mm, deg / cam.sigma_rotation_deg)
                     if name != result.extrinsics.reference and cam.sigma_translation_mm
                     and cam.sigma_rotation_deg else None)
            row += [f"{deg:.4f}", f"{mm:.3f}", "-" if ratio is None else f"{ratio:.1f}"]
        table.add_row(*row)
    _table_console().print(table)
    for name, why in result.extrinsics.unconnected.items():
        console.print(f"[yellow]not calibrated[/]: {name}: {why}")
    selection = result.set_selection
    if selection is not None:
        console.print(f"frame sets: kept {len(selection.kept)} of {selection.total} (runs of "
                      f"{selection.run_length} consecutive sets spread over the recording; "
                      "bundle.max_sets)", highlight=False, soft_wrap=True)
    ladder = result.self_calibration
    if ladder is not None and ladder.chosen.name != "nominal":
        chosen = next((f for f in ladder.fits if f.level == ladder.chosen), None)
        why = f": {chosen.reason}" if chosen is not None else ""
        console.print(shortened(f"self-calibration: refined {ladder.chosen.name}{why}"
                                + ("; markers detected again with the refined lens"
                                   if ladder.redetected else "")), highlight=False)
    clock = result.bundle.time if result.bundle is not None else None
    if clock is not None:
        console.print(shortened(
            f"time: {time_sentence(clock.to_dict(), result.extrinsics.reference)}"
            + ("" if clock.anchored else " (no timestamps: known up to a common scale factor)")),
            highlight=False, soft_wrap=True)
    if result.bundle is not None and (line := edge_offset_line(result.bundle.edge_offset)):
        console.print(shortened(line), highlight=False, soft_wrap=True)
    board = board_refined_entry(result).get("refined")
    if board and board["held"]:
        console.print(f"[yellow]board not refined[/]: {board['held']}")
    elif board:
        s = board["sigmas"]
        console.print(shortened(
            f"board: {glue_sentence(board)}; sigma {s['offset_mm'][0]:.2f} / "
            f"{s['offset_mm'][1]:.2f} mm, {s['rotation_deg']:.3f} deg, "
            f"{s['thickness_mm']:.2f} mm thick; corrected board file: board_refined.yaml"),
            highlight=False)
    if result.depth is not None and (line := depth_registration_line(result.depth)):
        console.print(shortened(line), highlight=False)
    if result.depth is not None and (line := fused_line(result.depth.agreement,
                                                         result.depth.beyond_board)):
        console.print(shortened(line), highlight=False, soft_wrap=True)
    if result.depth is not None and (result.depth.depth_models or result.depth.unmodelled):
        console.print(shortened(depth_model_line(result.depth.depth_models,
                                                 result.depth.unmodelled)),
                      highlight=False, soft_wrap=True)
    scales = result.depth.depth_scale_dict() if result.depth is not None else {}
    ratio = common_depth_scale({c: (e["factor"], e["sigma"]) for c, e in scales.items()})
    if ratio is not None:
        marker, square = (result.board.printed_lengths if result.board is not None
                          else (None, None))
        console.print(f"[red]board scale[/]: {board_scale_sentence(ratio, marker, square)}")
    if verdict:
        print_verdict(out)


def print_check_table(result, title: str) -> None:
    """Per camera: status, move and its sigma, pairs."""
    from rich.table import Table

    table = Table(title=title)
    for col in ("camera", "status", "moved mm", "moved deg", "chi2", "pairs"):
        table.add_column(col, justify="left" if col in ("camera", "status") else "right")
    style = {"in_place": "green", "moved": "bold red", "unknown": "yellow"}
    for c, r in result.cameras.items():
        if r.status == "unknown" or not math.isfinite(r.moved_mm):
            table.add_row(c, f"[{style[r.status]}]{r.status}[/]", "-", "-", "-", str(r.n_pairs))
            continue
        table.add_row(c, f"[{style[r.status]}]{r.status}[/]",
                      f"{r.moved_mm:.2f} ± {r.sigma_mm:.2f}",
                      f"{r.moved_deg:.3f} ± {r.sigma_deg:.3f}", f"{r.chi2:.1f}", str(r.n_pairs))
    console.print(table)
    for c in result.unknown:
        console.print(f"[yellow]not checked[/]: {c}: {result.cameras[c].reason}",
                      highlight=False, soft_wrap=True)
    for c in result.moved:
        if result.cameras[c].reason:
            console.print(f"[yellow]{c}[/] {result.cameras[c].reason}", highlight=False,
                          soft_wrap=True)


# --------------------------------------------------------------------------- convert
def print_conversion_report(report) -> None:
    """The per-camera counts of a :class:`~rgbd_calib.sources.ConversionReport` as a table,
    then its notes."""
    from rich.table import Table

    table = Table(
        title=f"{report.out}: {report.frames_written} frame sets "
        f"(sync tolerance {report.sync_tolerance_ms:.1f} ms)"
    )
    for col in ("camera", "read", "matched", "unmatched", "dropped", "no depth", "depth"):
        table.add_column(col, justify="right" if col not in ("camera", "depth") else "left")
    for name in report.cameras:
        c = report.counts[name]
        table.add_row(
            name,
            str(c.frames_read),
            str(c.matched),
            str(c.unmatched),
            str(c.dropped),
            str(c.without_depth),
            report.depth_source[name],
        )
    console.print(table)
    for note in report.notes:
        console.print(f"[yellow]note:[/] {note}", highlight=False)


def cli_convert(
    sources: Sequence[Path],
    out: Path,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    **options,
):
    """Run :func:`~rgbd_calib.sources.convert` (recordings, with ``options`` ``depth_models``,
    or videos with ``timestamps``, ``board``, ``step``, ``still_px_s``) with progress bars and
    print a table of the result."""
    from ..sources import convert

    with stage_progress() as progress:
        report = convert(sources, out, names, sync_tolerance_ms, progress, **options)
    print_conversion_report(report)
    return report


# --------------------------------------------------------------------------- record
RECORD_TIME_TIP = (
    "tip: without --hardware-sync the cameras capture up to half a frame apart (the table "
    "shows how far): hold the board still for a moment at each pose. calibrate's time model "
    "corrects a moving board from the timestamps this writes, but a still board is the most "
    "accurate (docs/accuracy.md, 'Time')."
)


def cli_record(
    out: Path,
    n_sets: int | None = None,
    mode: tuple[int, int, int] | None = None,
    hardware_sync: bool = False,
    board=None,
    names: Sequence[str] | None = None,
    device_source=None,
):
    """Run :func:`~rgbd_calib.sources.record.record` with a live table of board markers per
    camera."""
    from rich.live import Live
    from rich.table import Table

    from ..sources.record import DEFAULT_MODE, RecordStatus, record

    def table(status: RecordStatus) -> Table:
        t = Table(title=f"recording into {out}  (Ctrl-C to stop)")
        t.add_column("camera")
        t.add_column("markers", justify="right")
        for name, n in status.markers.items():
            t.add_row(name, "-" if n < 0 else str(n))
        t.caption = f"{status.sets_written} set(s) written; cameras {status.spread_ms:.1f} ms apart"
        return t

    if not hardware_sync:
        console.print(RECORD_TIME_TIP, highlight=False, soft_wrap=True)
    live: Live | None = None

    def show(status: RecordStatus) -> None:
        nonlocal live
        if live is None:  # only once the cameras stream: errors stay one clean line
            live = Live(table(status), console=console, refresh_per_second=4)
            live.start()
        live.update(table(status))

    try:
        report = record(
            out,
            n_sets,
            mode or DEFAULT_MODE,
            hardware_sync,
            board,
            names,
            device_source,
            status_callback=show,
        )
    finally:
        if live is not None:
            live.stop()
    how = "stopped by Ctrl-C" if report.interrupted else "done"
    console.print(
        f"{how}: {report.sets_written} set(s) of {len(report.cameras)} camera(s) in {report.out}"
    )
    for note in report.notes:
        console.print(f"[yellow]note:[/] {note}", highlight=False)
    return report


def edge_offset_line(offsets: dict[str, EdgeOffset]) -> str | None:
    """The console line of the detectors' edge offsets the bundle modelled (None: none)."""
    modelled = {c: e.offset_px for c, e in sorted(offsets.items()) if e.applied_px}
    if not modelled:
        return None
    lo, hi = min(modelled.values()), max(modelled.values())
    span = f"{lo:+.3f} px" if len(modelled) == 1 else f"{lo:+.3f}..{hi:+.3f} px"
    return (f"edge offset: the markers of {', '.join(modelled)} read {span} per edge off the "
            "board's geometry (blur, sharpening or ink spread); taken out of their corners "
            "(bundle.edge_offset)")
