"""The depth-only commands: ``refine`` (with ``--fix-others``) and ``check``, thin wrappers
around :mod:`rgbd_calib.pipelines.refine` and :mod:`rgbd_calib.pipelines.check` (registered
on the same ``app`` as :mod:`.commands`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .app import (
    ACCEPT_POOR_OPTION,
    EXIT_UNCHECKED,
    FORCE_OPTION,
    STRICT_OPTION,
    check_exit,
    check_method,
    check_output_folder,
    command,
    exit_on_poor,
    user_errors,
    warn_if_poor,
)
from .console import console, print_check_table, stage_progress, warn_line
from .options import NAMES_OPTION, SCHEDULER_OPTION, SYNC_OPTION, open_dataset


def _rig_now(sources: list[Path], out: Path, names: str | None, sync_tolerance_ms,
             scheduler: str | None, extrinsics: Path, force: bool | None = None):
    """What refine and check start from: the output folder (``force`` None: check, which
    writes no extrinsics.yaml; else refine's --force) and the scheduler checked before
    anything is read, the dataset of the rig as it is now opened (its images checked) with the
    intrinsics the calibration refined (its rig_refined.yaml, if any), the calibration's
    ``extrinsics`` and the depth corrections beside them (its depth_model.yaml, else its
    report.json's depth-scale factors): ``(dataset, extrinsics, corrections)``."""
    from ..core.parallel import check_scheduler
    from ..model.calib_folder import load_depth_corrections, with_refined_intrinsics
    from ..model.results import load_extrinsics

    # refine writes an extrinsics.yaml: never over the calibration it reads (check writes
    # check.json only, which may go beside it)
    over = ((extrinsics.parent, "calibration"),) if force is not None else ()
    check_output_folder(out, inputs=tuple((d, "dataset") for d in sources) + over, force=force)
    check_scheduler(scheduler)
    ds = open_dataset(sources, out, names, sync_tolerance_ms)
    ds.check_images()
    ds.rig, changed = with_refined_intrinsics(ds.rig, extrinsics.parent)
    if changed:
        console.print(f"intrinsics: the refined ones of {extrinsics.parent / 'rig_refined.yaml'}"
                      f" for {', '.join(changed)}", highlight=False, soft_wrap=True)
    calib = load_extrinsics(extrinsics, check_redundant=True)
    _check_camera_names(ds.rig.cameras, calib.cameras, sources, extrinsics)
    warn_if_poor(calib, extrinsics)
    return ds, calib, load_depth_corrections(extrinsics.parent)


def _check_camera_names(recorded, calibrated, sources: list[Path], extrinsics: Path) -> None:
    """The recording's cameras against the calibration's: none in common is a mistake (one
    line naming both lists, exit 2: every camera would be 'unknown' for want of a cloud);
    some of each unmatched is said (a camera added, or one renamed)."""
    from ..core.errors import ConfigError

    rec, cal = set(recorded), set(calibrated)
    where = sources[0] if len(sources) == 1 else "the recordings"
    if not rec & cal:
        raise ConfigError(
            f"{where}: its cameras ({', '.join(sorted(rec))}) match none of the calibration's "
            f"in {extrinsics} ({', '.join(sorted(cal))}); record with the calibration's camera "
            "names (rig.yaml, or --names for recordings)")
    if rec - cal and cal - rec:
        console.print(f"[yellow]warning[/]: {where}: cameras {', '.join(sorted(rec - cal))} are "
                      f"not in the calibration, and its {', '.join(sorted(cal - rec))} are not "
                      "recorded: renamed? They are not checked", highlight=False,
                      soft_wrap=True)


@command()
@user_errors
def refine(
    dataset: Annotated[
        list[Path],
        typer.Argument(
            help="Dataset folder with depth, or recordings (as for calibrate).",
            show_default=False,
        ),
    ],
    init: Annotated[
        Path,
        typer.Option(
            "--init", help="extrinsics.yaml to start from (hand-measured or an older calibration)."
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("refine_out"),
    method: Annotated[str, typer.Option(help="colored-icp or geometric.")] = "colored-icp",
    names: Annotated[str | None, NAMES_OPTION] = None,
    sync_tolerance_ms: Annotated[float | None, SYNC_OPTION] = None,
    board_file: Annotated[
        Path | None,
        typer.Option("--board", help="Board YAML of the starting calibration (default: the "
                     "thesis board); with its report.json's board poses it masks the board and "
                     "gives each camera's depth scale."),
    ] = None,
    fix_others: Annotated[
        bool,
        typer.Option("--fix-others", help="Only the cameras that moved since --init (found as "
                     "`check` finds them) are registered again, from a global alignment "
                     "(FPFH + RANSAC) then ICP, against the others, which keep --init exactly."),
    ] = False,
    tolerance_mm: Annotated[float, TOLERANCE_MM_OPTION] = 2.0,
    tolerance_deg: Annotated[float, TOLERANCE_DEG_OPTION] = 0.2,
    scheduler: Annotated[str | None, SCHEDULER_OPTION] = None,
    config: Annotated[Path | None, DEPTH_CONFIG_OPTION] = None,
    accept_poor: Annotated[bool, ACCEPT_POOR_OPTION] = False,
    strict: Annotated[bool, STRICT_OPTION] = False,
    force: Annotated[bool, FORCE_OPTION] = False,
) -> None:
    """Depth-only refinement of existing extrinsics (no board needed in view). Exit 0:
    verdict GOOD or CHECK; 3: POOR (written all the same); 5: CHECK with --strict; 2: an
    input error."""
    import math

    from ..model.board import thesis_board
    from ..model.board_file import load_board
    from ..outputs.writer import write_refine
    from ..pipelines.refine import refine as run_refine

    check_method(method)
    depth_config = _depth_config(config)
    ds, init_ext, scales = _rig_now(dataset, out, names, sync_tolerance_ms, scheduler, init,
                                    force)
    if fix_others:
        _fix_others(ds, init, init_ext, scales, method, out, tolerance_mm, tolerance_deg,
                    scheduler, depth_config)
        exit_on_poor(out, accept_poor, show=True, strict=strict)
        return
    b = load_board(board_file) if board_file else thesis_board()
    with stage_progress() as progress:
        result = run_refine(ds, init, method, depth_config, b, scales, progress=progress,
                            scheduler=scheduler)
    for kind, what in (("given", "from the calibration next to --init (its depth_model.yaml, "
                                 "else its report.json)"),
                       ("board", "estimated from the board in view"),
                       ("unknown", "unknown (not moved along what a scale error explains)")):
        if cams := [c for c, k in result.depth.scale_source.items() if k == kind]:
            console.print(f"depth scale {what}: {', '.join(cams)}")
    write_refine(result, out, warn=warn_line)
    for p in result.depth.pairs:
        state = "accepted" if p.accepted else f"rejected: {p.reason}"
        before, final = p.registration.rmse_before_mm, p.rmse_final_mm
        rmse = (f"rmse {before:.2f} -> {final:.2f} mm, "
                if before is not None and final is not None and math.isfinite(before)
                and math.isfinite(final) else "")
        console.print(f"{p.cam_a} -> {p.cam_b}: {rmse}{state}")
    outcome = result.outcome
    colour = {"refined": "green", "unchanged": "yellow", "check": "yellow"}[outcome["verdict"]]
    console.print(f"[{colour}]{outcome['verdict']}[/]: {outcome['message']}")
    console.print(f"results in {out}/ (extrinsics.yaml, report.html, report.json, "
                  "refine_report.json, fused.ply)")
    exit_on_poor(out, accept_poor, show=True, strict=strict)


DEPTH_CONFIG_OPTION = typer.Option(
    "--config", help="YAML overriding depth settings: its `depth:` section (the same file "
    "calibrate --config takes; config_resolved.yaml beside a result lists them all).")


def _depth_config(config: Path | None):
    """The ``depth`` settings of a ``--config`` file (None: the defaults); a bad file or key
    stops with one line naming it, before anything is read."""
    from ..core.config import load_config

    return load_config(config).depth if config is not None else None


TOLERANCE_MM_OPTION = typer.Option(
    "--tolerance-mm", help="A camera counts as moved only beyond this shift (mm) or turn, "
    "and only if the depth says so significantly (chi-square 6 dof, 0.1 %).")
TOLERANCE_DEG_OPTION = typer.Option("--tolerance-deg", help="Same, turn (deg).")


def _run_check(ds, calib, scales, method, tolerance_mm, tolerance_deg, scheduler=None,
               depth_config=None, calib_dir: Path | None = None):
    """check, the board (evidence where in view) and its detector edge offsets the
    calibration's in ``calib_dir``."""
    from ..model.calib_folder import calibration_board, load_edge_offsets
    from ..pipelines.check import check
    from ..solve.moved import Tolerance

    board, where = calibration_board(calib_dir or Path("."), ds.path)
    offsets = load_edge_offsets((calib_dir or Path(".")) / "report.json")
    with stage_progress() as progress:
        run = check(ds, calib, method, depth_config, Tolerance(tolerance_mm, tolerance_deg),
                    scales, progress=progress, scheduler=scheduler, board=board,
                    edge_offsets=offsets)
    used = run.result.board.get("frame_sets", 0)
    console.print(f"board: {where}; " + (f"seen by two cameras or more in {used} frame sets: "
                  "evidence beside the depth" if used else "not seen by two cameras in one "
                  "frame set: depth alone"), highlight=False, soft_wrap=True)
    return run


def _fix_others(ds, init: Path, calib, scales, method, out, tolerance_mm, tolerance_deg,
                scheduler=None, depth_config=None):
    """refine --fix-others: check, then re-register only the moved cameras."""
    from ..core.progress import start
    from ..outputs.writer import DepthOnlyRun, write_fix_outputs
    from ..pipelines.check import fix_moved
    from ..pipelines.refine import fix_verdict

    run = _run_check(ds, calib, scales, method, tolerance_mm, tolerance_deg, scheduler,
                     depth_config, init.parent)
    print_check_table(run.result, f"{ds.path} against {init}")
    unknown = {c for c, k in run.scale_source.items() if k == "unknown"}
    with stage_progress() as progress:
        tick = start(progress, "re-registering the moved cameras", 1)
        fix = fix_moved(run.clouds, calib, run.result, run.overlaps, method, depth_config,
                        unknown_scale=unknown, scheduler=scheduler, links=run.links,
                        sensor_poses=run.sensor_poses)
        tick(1)
    moved, fixed, pairs = run.result.moved, fix.extrinsics, fix.pairs
    verdict = fix_verdict(calib, fixed, moved, pairs, fix.unconfirmed)
    status = ({"status": "skipped", "reason": "no camera moved beyond the tolerance",
               "weak_cameras": {}} if not moved else
              {"status": "used", "reason": None, "weak_cameras": {}}
              if any(p.accepted for p in pairs) else
              {"status": "fallback", "reason": "no pair of a moved camera fits after "
               "re-registration", "weak_cameras": {}})
    depth_only = DepthOnlyRun(ds, init, method, verdict, pairs, run.scale_source, scales,
                              status, timings_s=run.result.timings_s, moved=moved)
    write_fix_outputs(fixed, run, pairs, out, method, init, verdict, depth_only=depth_only,
                      warn=warn_line)
    colour = {"refined": "green", "unchanged": "yellow", "check": "yellow"}[verdict["verdict"]]
    console.print(f"[{colour}]{verdict['verdict']}[/]: {verdict['message']}", highlight=False,
                  soft_wrap=True)
    console.print(f"results in {out}/ (extrinsics.yaml, report.html, report.json, "
                  "refine_report.json, fused.ply)")


@command()
@user_errors
def check(
    dataset: Annotated[
        list[Path],
        typer.Argument(help="A frame set of the rig as it is now (a dataset folder with depth, "
                       "or recordings as for calibrate); no board needed. A short still "
                       "recording (8+ frames) is better than one frame.", show_default=False),
    ],
    calib: Annotated[
        Path,
        typer.Option("--calib", help="The calibration to check: its output folder (with "
                     "extrinsics.yaml and report.json) or an extrinsics.yaml."),
    ],
    out: Annotated[Path, typer.Option("--out", help="Output folder (check.json).")] = Path(
        "check_out"),
    method: Annotated[str, typer.Option(help="colored-icp or geometric.")] = "colored-icp",
    tolerance_mm: Annotated[float, TOLERANCE_MM_OPTION] = 2.0,
    tolerance_deg: Annotated[float, TOLERANCE_DEG_OPTION] = 0.2,
    names: Annotated[str | None, NAMES_OPTION] = None,
    sync_tolerance_ms: Annotated[float | None, SYNC_OPTION] = None,
    scheduler: Annotated[str | None, SCHEDULER_OPTION] = None,
    config: Annotated[Path | None, DEPTH_CONFIG_OPTION] = None,
) -> None:
    """Has a camera moved since the calibration? Exit 0: every camera checked and in place;
    1: some moved (named); 4: none moved, but some could not be checked; 2: an input error."""
    from ..core.errors import ConfigError
    from ..outputs.writer import write_check_outputs

    check_method(method)
    if tolerance_mm < 0 or tolerance_deg < 0:
        raise ConfigError("--tolerance-mm / --tolerance-deg must be >= 0")
    path = calib / "extrinsics.yaml" if calib.is_dir() else calib
    if not path.is_file():
        raise ConfigError(f"{calib}: no extrinsics.yaml; give a calibrate output folder or an "
                          "extrinsics.yaml with --calib")
    depth_config = _depth_config(config)
    ds, ext, scales = _rig_now(dataset, out, names, sync_tolerance_ms, scheduler, path)
    run = _run_check(ds, ext, scales, method, tolerance_mm, tolerance_deg, scheduler,
                     depth_config, path.parent)
    print_check_table(run.result, f"{ds.path} against {path}")
    if unknown := [c for c, k in run.scale_source.items() if k == "unknown"]:
        console.print(f"depth scale unknown (no report.json with depth_scale_factor next to "
                      f"{path.name}): {', '.join(unknown)}", highlight=False, soft_wrap=True)
    write_check_outputs(run, out, path)
    moved, unchecked = run.result.moved, run.result.unknown
    if moved:
        console.print(f"[bold red]moved[/]: {', '.join(moved)} -> put back with: rgbd-calib "
                      f"refine {' '.join(map(str, dataset))} --init {path} --fix-others "
                      f"--out DIR", highlight=False, soft_wrap=True)
    elif unchecked:
        console.print(f"[green]in place[/]: every checked camera within {tolerance_mm} mm / "
                      f"{tolerance_deg} deg", highlight=False)
    if unchecked:  # never "all in place": say which were not checked, and how to check them
        console.print(f"[yellow]not checked[/]: {', '.join(unchecked)} (neither their depth "
                      "pairs nor the board could tell; reasons in check.json)"
                      + ("" if moved else f": exit {EXIT_UNCHECKED}") + ". To check them, "
                      "record a few seconds with the board held still where each of them and "
                      "a neighbour see it, or put a few boxes in the scene (walls and floor "
                      "alone leave depth pairs free to slide)", highlight=False, soft_wrap=True)
    if not moved and not unchecked:
        console.print(f"[green]in place[/]: every camera within {tolerance_mm} mm / "
                      f"{tolerance_deg} deg", highlight=False)
    console.print(f"check: {out / 'check.json'}", highlight=False)
    raise typer.Exit(check_exit(moved, unchecked))
