"""The ``rgbd-calib`` command line: thin wrappers around the library API.

Heavy imports happen inside the commands so ``--help`` stays fast. Every user mistake is a
:class:`~rgbd_calib.core.errors.RgbdCalibError`, printed as one line with a non-zero exit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .app import (
    ACCEPT_POOR_OPTION,
    FORCE_OPTION,
    STRICT_OPTION,
    app,
    check_output_folder,
    command,
    exit_on_poor,
    parse_resolution,
    user_errors,
    warn_if_poor,
    workers_ignore_ctrl_c,
)
from .console import (
    console,
    print_summary,
    print_verdict,
    stage_progress,
    warn_line,
)
from .options import NAMES_OPTION, SCHEDULER_OPTION, SYNC_OPTION, name_list, open_dataset


@command()
@user_errors
def board(
    board_file: Annotated[Path, typer.Argument(help="Board YAML (grid or explicit form).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("board_print"),
    dpi: Annotated[int, typer.Option(help="Resolution of the PNG files (dots per inch).")] = 300,
    page: Annotated[
        str | None,
        typer.Option(
            help="Page size, e.g. A3 or A4-landscape; default: the smallest A size that fits."
        ),
    ] = None,
    fix_winding: Annotated[
        bool, typer.Option(help="Reorder mirrored markers instead of rejecting them.")
    ] = False,
    measured: Annotated[
        tuple[float, float] | None,
        typer.Option(metavar="ACROSS_MM DOWN_MM",
                     help="The printed front sheet as measured (the span its printed line "
                     "names): write OUT/board.yaml, the board file rescaled to it with its "
                     "print_scale_sigma, instead of the prints."),
    ] = None,
    measured_sigma: Annotated[
        float, typer.Option(metavar="MM", help="1 sigma of one --measured reading (mm).")
    ] = 0.3,
) -> None:
    """Write the board's faces as true-scale PDFs and PNGs, ready to print and glue; with
    --measured, the board file rescaled to the printed sheet instead."""
    from ..model.board_file import load_board
    from ..outputs.printing import measuring_line, write_printable_board

    check_output_folder(out)
    b = load_board(board_file, fix_winding=fix_winding)
    if measured is not None:
        _write_measured_board(b, out, measured, measured_sigma)
        return
    result = write_printable_board(b, out, dpi=dpi, page=page)
    for path in result.files:
        typer.echo(path)
    if (line := measuring_line(b)) is not None:
        typer.echo(line)


def _write_measured_board(b, out: Path, measured: tuple[float, float], sigma_mm: float) -> None:
    """``board --measured``: the board file rescaled to its printed front sheet, written as
    ``out/board.yaml``, and what was measured said in two lines (three for a stretched
    print)."""
    from ..core.errors import ConfigError
    from ..model.board_file import save_board
    from ..model.board_print import measured_print_scale, rescaled_board

    scale = measured_print_scale(b, measured, sigma_mm)
    path = Path(out) / "board.yaml"
    if b.source is not None and path.resolve() == Path(b.source).resolve():
        raise ConfigError(f"{path}: --out would rescale this board file in place (a second run "
                          "would scale it twice); choose another --out folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    save_board(rescaled_board(b, scale.scale, scale.sigma), path)
    typer.echo(f"the print is {scale.scale:.5f} x the file's size +- {scale.sigma:.5f} "
               f"(across {scale.across:.5f}, down {scale.down:.5f})")
    if scale.stretched:
        warn_line(f"the print is stretched: {abs(scale.across - scale.down):.2%} more "
                  f"{'across' if scale.across > scale.down else 'down'} than the other way "
                  "(a printer's paper feed); one scale cannot hold it, so the file takes "
                  "the mean and its sigma covers half the difference. A print at actual "
                  "size on another printer, measured again, avoids it")
    typer.echo(f"wrote {path}: every printed length x {scale.scale:.5f}, print_scale_sigma "
               f"{scale.sigma:.5f}; calibrate with --board {path} (or copy it into the "
               "dataset folder as board.yaml)")


# the options of `synth` (its imperfections shown in a panel of their own)
IMPERFECTIONS_PANEL = "Imperfections (docs/synthetic.md)"
DISTORTION_OPTION = typer.Option(
    metavar="K1 K2 P1 P2 K3",
    help="true lens distortion of every camera (OpenCV order), rendered "
    "exactly per pixel ray; e.g. 0.1 -0.2 0.001 -0.001 0.05.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
FISHEYE_OPTION = typer.Option(
    metavar="K1 K2 K3 K4",
    help="true fisheye lens of every camera instead (equidistant, cv2.fisheye's and Kalibr's "
    "pinhole-equi k1..k4; rig.yaml lists model: fisheye); e.g. 0.05 -0.01 0.003 -0.0005.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
RIG_DISTORTION_OPTION = typer.Option(
    help="What rig.yaml lists with --distortion: zeros (as the D435 colour stream "
    "reports) or truth.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
INTRINSICS_ERROR_OPTION = typer.Option(
    metavar="F_PCT PX",
    help="rig.yaml's fx, fy off by one factor within +-F_PCT % and cx, "
    "cy each off by up to +-PX pixels (seeded); the images use the truth.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
GLUE_OPTION = typer.Option(
    metavar="DX_MM DY_MM ROT_DEG",
    help="the back sheet rotated by ROT_DEG about the board normal "
    "(through the back grid's centre) and shifted by DX_MM, DY_MM along the board's "
    "x, y; the board file stays nominal.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
THICKNESS_ERROR_OPTION = typer.Option(
    metavar="MM",
    help="the panel is MM thicker (negative: thinner) than the board file.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
PRINT_SCALE_OPTION = typer.Option(
    metavar="S",
    help="both faces printed S times the board file's size (scaled about "
    "the board origin), e.g. 0.995; the board file stays nominal.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
INK_SPREAD_OPTION = typer.Option(
    metavar="MM",
    help="the printer's ink spreads MM beyond the board file's black edges (both faces; "
    "negative: thinner): every marker looks larger by MM per edge, e.g. 0.1; ArUco boards.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
FACE_ERROR_OPTION = typer.Option(
    metavar="MM DEG",
    help="multi-face target (a cube, an L): every face but the first moved off its "
    "board-file pose by MM and turned by DEG, each in a seeded direction of its own "
    "(a hand-built target); the board file stays nominal.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
MOTION_OPTION = typer.Option(
    metavar="SPEED_MPS RATE_DPS",
    help="the board moves during each frame set, as a hand waves it: SPEED_MPS m/s along "
    "and RATE_DPS deg/s about a seeded direction per set (e.g. 0.3 30); needs "
    "--sync-offset-ms or --rolling-shutter-ms to show in the images.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
SYNC_OFFSET_OPTION = typer.Option(
    metavar="MS",
    help="cameras not in sync: each one's clock off the reference camera's by a seeded "
    "offset within +-MS ms (e.g. 16: half a frame at 30 fps).",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
ROLLING_SHUTTER_OPTION = typer.Option(
    metavar="MS",
    help="rolling-shutter colour sensors: rows exposed one after another over MS ms, top "
    "to bottom, each rendered at its own time (e.g. 25); depth stays a global shutter.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
TIMESTAMP_JITTER_OPTION = typer.Option(
    metavar="MS",
    help="with a time option on, each camera's timestamps.csv stamps its frames at "
    "t_f + offset + a Gaussian error of sigma MS ms (board positions 1 s apart, a burst's "
    "frame sets 1000/FPS ms, --frame-rate); "
    "ground_truth.yaml keeps the exact offsets.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
BURST_OPTION = typer.Option(
    metavar="N",
    help="a continuous recording: each board position held for N consecutive frame sets at "
    "--frame-rate (30 fps), the board moving along one trajectory through them (with "
    "--motion), as a video kept whole around each pose; timestamps.csv says so (positions "
    "1 s apart).",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
FRAME_RATE_OPTION = typer.Option(
    metavar="FPS",
    help="the recording's frame rate: a --burst's consecutive frame sets are 1/FPS s apart "
    "(e.g. 6 for USB webcams; default 30, a D435i's).",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
ACCELERATION_OPTION = typer.Option(
    metavar="MPS2 DPS2",
    help="the board accelerates along its trajectory as a hand moves it: MPS2 m/s^2 in a "
    "seeded direction and DPS2 deg/s^2 about its turn axis, per position (e.g. 1 100).",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
DEPTH_OFFSET_OPTION = typer.Option(
    "--depth-disparity-offset", metavar="PX",
    help="each camera's depth off by a disparity offset d0 uniform in +-PX px (seeded): "
    "a depth error of about z^2 d0 / (f B), e.g. 0.1.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
DEPTH_FIELD_OPTION = typer.Option(
    "--depth-disparity-field", metavar="PX",
    help="each camera's disparity offset varies over the image: dx x + dy y + dxx x^2 + "
    "dxy x y + dyy y^2 (x = X/Z, y = Y/Z), each coefficient uniform in +-PX px.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
DEPTH_POSE_OPTION = typer.Option(
    "--depth-pose-error", metavar="DEG MM",
    help="each camera's depth-to-colour pose off: a rotation vector and a shift with each "
    "component uniform in +-DEG deg and +-MM mm, e.g. 0.2 1.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)
BOARD_VOLUME_OPTION = typer.Option(
    metavar="S",
    help="move the board through S times the layout's volume (about its centre): "
    "e.g. 2.5 on the ring brings it near the cameras and over more of each image "
    "(docs/synthetic.md).",
)
CLOSEUPS_OPTION = typer.Option(
    metavar="N",
    help="N extra frame sets per camera with the board near it, reaching its image's "
    "corners and edges in turn, as a user records to calibrate a lens "
    "(docs/synthetic.md).",
)
BUMP_OPTION = typer.Option(
    metavar="NAME:MM:DEG",
    help="camera NAME knocked after the calibration: shifted MM and turned DEG in a "
    "seeded direction (repeat for more cameras); render the same seed without it to "
    "calibrate, with it to test `check` and `refine --fix-others`.",
    rich_help_panel=IMPERFECTIONS_PANEL,
)


@command()
@user_errors
def synth(
    out: Annotated[
        Path, typer.Argument(help="Output dataset folder (must not exist or be empty).")
    ],
    layout: Annotated[
        str, typer.Option(help="thesis-line, race, race16 (16 cameras, two tiers) or ring.")
    ] = "race",
    frames: Annotated[int, typer.Option(help="Number of synchronised frame sets.")] = 40,
    seed: Annotated[int, typer.Option(help="Random seed (rig jitter, board motion, noise).")] = 0,
    resolution: Annotated[
        str | None,
        typer.Option(help="WIDTHxHEIGHT; default: 848x480 for race, 1280x720 otherwise."),
    ] = None,
    board_file: Annotated[
        Path | None, typer.Option("--board", help="Board YAML; default: the dataset's "
                                  "board.yaml (synth and convert --board write it), else the "
                                  "thesis board.")
    ] = None,
    depth_bias: Annotated[
        float,
        typer.Option(help="Max |relative depth-scale error| per camera, e.g. 0.006 for +-0.6%."),
    ] = 0.0,
    depth_disparity_offset: Annotated[float, DEPTH_OFFSET_OPTION] = 0.0,
    depth_disparity_field: Annotated[float, DEPTH_FIELD_OPTION] = 0.0,
    depth_pose_error: Annotated[tuple[float, float], DEPTH_POSE_OPTION] = (0.0, 0.0),
    blur: Annotated[float, typer.Option(help="Lens blur sigma (px).")] = 0.6,
    noise: Annotated[float, typer.Option(help="Colour noise sigma (8-bit DN).")] = 2.0,
    depth_dropout: Annotated[float, typer.Option(help="Fraction of depth pixels lost.")] = 0.02,
    drop_rate: Annotated[float, typer.Option(help="Probability a camera misses a frame.")] = 0.0,
    cameras: Annotated[int | None, typer.Option(help="Camera count (ring layout).")] = None,
    workers: Annotated[int | None, typer.Option(help="Processes; default all cores.")] = None,
    distortion: Annotated[
        tuple[float, float, float, float, float] | None, DISTORTION_OPTION
    ] = None,
    fisheye: Annotated[tuple[float, float, float, float] | None, FISHEYE_OPTION] = None,
    rig_distortion: Annotated[str, RIG_DISTORTION_OPTION] = "zeros",
    intrinsics_error: Annotated[tuple[float, float], INTRINSICS_ERROR_OPTION] = (0.0, 0.0),
    glue: Annotated[tuple[float, float, float], GLUE_OPTION] = (0.0, 0.0, 0.0),
    thickness_error: Annotated[float, THICKNESS_ERROR_OPTION] = 0.0,
    print_scale: Annotated[float, PRINT_SCALE_OPTION] = 1.0,
    ink_spread: Annotated[float, INK_SPREAD_OPTION] = 0.0,
    face_error: Annotated[tuple[float, float], FACE_ERROR_OPTION] = (0.0, 0.0),
    board_volume: Annotated[float, BOARD_VOLUME_OPTION] = 1.0,
    closeups: Annotated[int, CLOSEUPS_OPTION] = 0,
    bump: Annotated[list[str] | None, BUMP_OPTION] = None,
    motion: Annotated[tuple[float, float], MOTION_OPTION] = (0.0, 0.0),
    sync_offset_ms: Annotated[float, SYNC_OFFSET_OPTION] = 0.0,
    rolling_shutter_ms: Annotated[float, ROLLING_SHUTTER_OPTION] = 0.0,
    timestamp_jitter_ms: Annotated[float, TIMESTAMP_JITTER_OPTION] = 0.5,
    burst: Annotated[int, BURST_OPTION] = 1,
    acceleration: Annotated[tuple[float, float], ACCELERATION_OPTION] = (0.0, 0.0),
    frame_rate: Annotated[float, FRAME_RATE_OPTION] = 30.0,
) -> None:
    """Render a synthetic RGB-D rig with ground truth (dataset folder + ground_truth.yaml).

    By default the cameras are ideal and rig.yaml is exact; the imperfection options render
    real-world errors and record their truth in ground_truth.yaml (docs/synthetic.md)."""
    from ..model.board import thesis_board
    from ..model.board_file import load_board
    from ..synth.render import SynthParams, synthesize

    check_output_folder(out, "the output dataset folder")
    workers_ignore_ctrl_c()
    from ..core.errors import ConfigError

    if fisheye is not None and distortion is not None:
        raise ConfigError("--distortion and --fisheye: give one lens (OpenCV's k1 k2 p1 p2 k3, "
                          "or the fisheye's k1..k4)")
    params = SynthParams(
        resolution=parse_resolution(resolution),
        blur_sigma_px=blur,
        color_noise_dn=noise,
        depth_bias=depth_bias,
        depth_disparity_offset_px=depth_disparity_offset,
        depth_disparity_field_px=depth_disparity_field,
        depth_pose_error=depth_pose_error,
        depth_dropout=depth_dropout,
        drop_rate=drop_rate,
        cameras=cameras,
        distortion=fisheye if fisheye is not None else distortion,
        lens="fisheye" if fisheye is not None else "opencv",
        rig_distortion=rig_distortion,
        intrinsics_error=intrinsics_error,
        glue=glue,
        thickness_error_mm=thickness_error,
        print_scale=print_scale,
        ink_spread_mm=ink_spread,
        face_error=face_error,
        board_volume=board_volume,
        closeups=closeups,
        bump=tuple(_parse_bump(text) for text in bump or ()),
        motion=motion,
        sync_offset_ms=sync_offset_ms,
        rolling_shutter_ms=rolling_shutter_ms,
        timestamp_jitter_ms=timestamp_jitter_ms,
        burst=burst,
        acceleration=acceleration,
        frame_rate=frame_rate,
    )
    b = load_board(board_file) if board_file else thesis_board()
    with stage_progress() as progress:
        ds = synthesize(out, layout, frames, seed, b, params, workers, progress=progress)
    extra = f" + {closeups} close-ups per camera" if closeups else ""
    extra += f", each {burst} consecutive frame sets" if burst > 1 else ""
    console.print(f"wrote {len(ds.rig.cameras)} cameras x {frames} frames{extra} to {ds.path}")


def _parse_bump(text: str) -> tuple[str, float, float]:
    """``--bump NAME:MM:DEG`` as ``(name, mm, deg)``."""
    from ..core.errors import ConfigError

    name, _, rest = text.partition(":")
    try:
        mm, deg = (float(x) for x in rest.split(":"))
    except ValueError:
        raise ConfigError(f"--bump {text!r}: give NAME:MM:DEG, e.g. left2:50:5") from None
    return name, mm, deg


def _dataset_board(ds):
    """Without --board: the dataset's own board.yaml (synth, convert --board), else the thesis
    board; with the console line that says which."""
    from ..model.board import thesis_board
    from ..model.board_file import dataset_board_file, load_board

    own = dataset_board_file(ds.path)
    if own is not None:
        return load_board(own), f"board: {own} (the dataset's; --board overrides it)"
    return thesis_board(), ("board: the thesis board (no --board, and the dataset has no "
                            "board.yaml); pass --board BOARD.yaml for any other")


@command()
@user_errors
def calibrate(
    dataset: Annotated[
        list[Path],
        typer.Argument(
            help="Dataset folder (rig.yaml + <camera>/color, depth), or recordings: RealSense "
            ".bag/.db3 files (one per camera) or ROS 1/ROS 2 bags, converted once into "
            "OUT/cache/recordings.",
            show_default=False,
        ),
    ],
    board_file: Annotated[
        Path | None, typer.Option("--board", help="Board YAML; default: the thesis board.")
    ] = None,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("calib_out"),
    config: Annotated[
        Path | None, typer.Option(help="YAML overriding any calibration setting.")
    ] = None,
    method: Annotated[
        str | None, typer.Option(help="bundle (default) or posegraph (the thesis method).")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="Detection processes; default all cores.")
    ] = None,
    refine: Annotated[
        str | None,
        typer.Option(
            help="Depth refinement: colored-icp (default when there is depth), geometric or none."
        ),
    ] = None,
    intrinsics: Annotated[
        str | None,
        typer.Option(
            help="auto (default): estimate them in the bundle adjustment only when the "
            "views disagree camera by camera and the corners fit better for it (writes "
            "rig_refined.yaml then); fixed: trust the rig.yaml intrinsics; refine: always "
            "estimate them. A camera whose rig.yaml gives only width/height is calibrated from "
            "scratch from its own views first (auto then refines; fixed holds that estimate)."
        ),
    ] = None,
    board_model: Annotated[
        str | None,
        typer.Option(
            "--board-model",
            help="auto (default): estimate where the back sheet really is (offset, "
            "rotation, thickness) when that keeps more cameras or fits the corners better "
            "(writes board_refined.yaml then); fixed: the board file is exact; refine: "
            "always estimate it.",
        ),
    ] = None,
    time: Annotated[
        str | None,
        typer.Option(
            "--time",
            help="auto (default): when the views disagree, also try each camera's clock "
            "offset and rolling-shutter readout and each frame set's board motion, kept when "
            "the corners fit better for it (cameras without a sync cable, a board waved by "
            "hand); fixed: every camera captured at the frame set's instant; refine: always "
            "estimate them. The cameras' timestamps.csv, when the dataset has them, fix the "
            "clocks' scale.",
        ),
    ] = None,
    fix: Annotated[
        Path | None,
        typer.Option(
            help="extrinsics.yaml of an earlier calibration: "
            "hold its cameras fixed (adding cameras)."
        ),
    ] = None,
    names: Annotated[str | None, NAMES_OPTION] = None,
    sync_tolerance_ms: Annotated[float | None, SYNC_OPTION] = None,
    scheduler: Annotated[str | None, SCHEDULER_OPTION] = None,
    accept_poor: Annotated[bool, ACCEPT_POOR_OPTION] = False,
    strict: Annotated[bool, STRICT_OPTION] = False,
    force: Annotated[bool, FORCE_OPTION] = False,
) -> None:
    """Calibrate every camera's extrinsics; writes extrinsics.yaml, report.json and exports.
    Exit 0: verdict GOOD or CHECK; 3: POOR (written all the same); 5: CHECK with --strict;
    2: an input error."""
    from ..core.config import load_config
    from ..core.parallel import check_scheduler
    from ..model.board_file import load_board
    from ..model.results import load_extrinsics

    check_output_folder(out, inputs=tuple((d, "dataset") for d in dataset)
                        + (((fix.parent, "calibration of --fix"),) if fix else ()), force=force)
    cfg = load_config(config, method=method, workers=workers, refine=refine,
                      scheduler=scheduler,
                      **{"bundle.intrinsics": intrinsics, "bundle.board": board_model,
                         "bundle.time": time})
    check_scheduler(cfg.scheduler)
    b = load_board(board_file) if board_file else None
    ds = open_dataset(dataset, out, names, sync_tolerance_ms)
    board_note = None
    if b is None:
        b, board_note = _dataset_board(ds)
    fixed = None
    if fix is not None:
        prior = load_extrinsics(fix, check_redundant=True)
        _check_fixed(prior, ds.rig, fix)
        warn_if_poor(prior, fix)
        fixed = {n: c.T_ref_cam for n, c in prior.cameras.items() if n in ds.rig.cameras}
    ds.check_images()
    workers_ignore_ctrl_c()
    result = _calibrate_and_write(ds, b, cfg, out, fixed)
    if board_note:  # after the run: a failing one ends on its error line alone
        console.print(board_note, highlight=False, soft_wrap=True)
    print_summary(result, out)
    exit_on_poor(out, accept_poor, strict=strict)


def _check_fixed(prior, rig, path: Path) -> None:
    """``--fix`` poses are in the prior's reference frame: it must be this rig's reference,
    and at least one of its cameras must be in the dataset."""
    from ..core.errors import ConfigError

    if prior.reference != rig.reference:
        raise ConfigError(
            f"{path}: its poses are relative to {prior.reference!r} but the dataset's rig.yaml "
            f"uses reference {rig.reference!r}; set the same reference in rig.yaml"
        )
    if not any(n in rig.cameras and n != rig.reference for n in prior.cameras):
        raise ConfigError(
            f"{path}: none of its cameras ({', '.join(prior.cameras)}) besides the reference "
            "is in the dataset; check the --fix file"
        )


def _calibrate_and_write(ds, board, cfg, out: Path, fixed=None):
    """Run the pipeline and write its outputs, with progress bars on every long step. A run
    that stops on bad input (a wrong board, a rig no view links) leaves ``out`` as it found
    it: the detection cache it started is removed with the folder it created."""
    import shutil

    from ..core.errors import RgbdCalibError
    from ..outputs.writer import write_outputs
    from ..pipelines.calibrate import calibrate as run_calibration

    created = next((p for p in (out, out / "cache") if not p.exists()), None)  # this run's
    with stage_progress() as progress:
        try:
            result = run_calibration(
                ds, board, cfg, cache_dir=out / "cache", fixed_cameras=fixed, progress=progress
            )
        except RgbdCalibError:
            if created is not None:
                shutil.rmtree(created, ignore_errors=True)
            raise
        write_outputs(result, ds.rig, out, progress=progress, warn=warn_line)
    return result


@command()
@user_errors
def report(
    out: Annotated[Path, typer.Argument(help="Output folder of an earlier calibrate run.")],
) -> None:
    """Rebuild report.html (and report.json) from the saved results of a calibration."""
    from ..outputs.report import rebuild_report

    with stage_progress() as progress:
        path = rebuild_report(out, progress=progress)
    console.print(f"report: {path}")


@command()
@user_errors
def posegraph(
    nodes: Annotated[Path, typer.Argument(help="Thesis Nodes.csv (initial guesses).")],
    edges: Annotated[Path, typer.Argument(help="Thesis Edges.csv (T_cam_board per row).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("posegraph_out"),
    kernel: Annotated[str, typer.Option(help="cauchy, huber, tukey, gm or none.")] = "cauchy",
    optimizer: Annotated[str, typer.Option(help="lm or gnc.")] = "lm",
    accept_poor: Annotated[bool, ACCEPT_POOR_OPTION] = False,
    strict: Annotated[bool, STRICT_OPTION] = False,
) -> None:
    """Robustly optimise a thesis-format pose graph (Nodes.csv / Edges.csv). Exit codes as
    calibrate's: 3 for a POOR verdict (a camera no edge links), 5 for CHECK with --strict."""
    from pydantic import ValidationError

    from ..core.config import PoseGraphConfig
    from ..core.errors import ConfigError
    from ..outputs.writer import write_posegraph_outputs
    from ..pipelines.posegraph import run_posegraph

    try:
        cfg = PoseGraphConfig(kernel=kernel, optimizer=optimizer)
    except ValidationError as exc:
        raise ConfigError(f"options: {exc.errors()[0]['msg']}") from None
    check_output_folder(out)
    run = run_posegraph(nodes, edges, cfg)
    write_posegraph_outputs(run, out)
    console.print(
        f"edges: {len(run.edges)}, stale: {len(run.stale_edges)}, "
        f"outliers: {len(run.outlier_edges)}"
    )
    for name, cam in run.extrinsics.cameras.items():
        t = cam.T_ref_cam[:3, 3]
        console.print(
            f"{name}: t = [{t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}] m, sigma "
            f"{cam.sigma_rotation_deg:.3f} deg / {cam.sigma_translation_mm:.2f} mm"
        )
    console.print(f"results in {out}/ (extrinsics.yaml, posegraph_report.json, exports/)")
    exit_on_poor(out, accept_poor, show=True, strict=strict)


# the demo's scene of interest per layout (m): a race rig fuses the race, out to the cameras
# across it (2.0-2.2 m away), as a user sets depth.clouds.max_range_m; the room's walls behind them
# (3.8 m) are beyond any board pose the thesis board can be detected at in 848 x 480
DEMO_SCENE_RANGE_M = {"race": 2.2}


@command()
@user_errors
def demo(
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("demo_out"),
    layout: Annotated[
        str, typer.Option(help="thesis-line, race, race16 (16 cameras, two tiers) or ring.")
    ] = "race",
    frames: Annotated[int, typer.Option(help="Frame sets to render.")] = 16,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    accept_poor: Annotated[bool, ACCEPT_POOR_OPTION] = False,
    strict: Annotated[bool, STRICT_OPTION] = False,
) -> None:
    """Render a small synthetic rig, calibrate it and compare with its ground truth (a re-run
    with the same options reuses the render and the detections). The race keeps depth within
    2.2 m of each camera (depth.clouds.max_range_m: the race, not the room's walls; in
    config_resolved.yaml). Exit codes as calibrate's."""
    from ..model.board import thesis_board
    from ..model.dataset import FolderDataset
    from ..synth.render import SynthParams, load_ground_truth, synthesize_cached

    check_output_folder(out)
    workers_ignore_ctrl_c()
    with stage_progress() as progress:
        dataset, reused = synthesize_cached(out / "dataset", layout, frames, seed, thesis_board(),
                                            SynthParams(depth_bias=0.004), progress=progress)
    if reused:
        console.print(f"reusing the rendered rig in {dataset}/ (same options)", highlight=False)
    ds = FolderDataset(dataset)
    board, _ = _dataset_board(ds)  # the render's board file, as calibrate reads it
    cfg = None
    if layout in DEMO_SCENE_RANGE_M:
        from ..core.config import load_config

        cfg = load_config(None, **{"depth.clouds.max_range_m": DEMO_SCENE_RANGE_M[layout]})
    result = _calibrate_and_write(ds, board, cfg, out / "calibration")
    print_summary(result, out / "calibration", verdict=False, truth=load_ground_truth(dataset))
    print_verdict(out / "calibration")
    exit_on_poor(out / "calibration", accept_poor, strict=strict)


@command()
@user_errors
def convert(
    sources: Annotated[
        list[Path],
        typer.Argument(help="RealSense .bag/.db3 files (one per camera), ROS 1/ROS 2 bags, or "
                       "video files (one per camera: .mp4, .avi, ...)."),
    ],
    out: Annotated[Path, typer.Option("--out", help="Dataset folder to write.")],
    names: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated camera names, in source order (default: serial / ROS namespace)."
        ),
    ] = None,
    sync_tolerance_ms: Annotated[
        float | None,
        typer.Option(
            help="Largest timestamp gap between cameras of one frame set (ms); default half a "
            "frame period."
        ),
    ] = None,
    timestamps: Annotated[
        Path | None,
        typer.Option(help="Videos: CSV sync_index,cam_id,frame_index,frame_time grouping the "
                     "frames into sets (default: frame k of every video is set k)."),
    ] = None,
    board_file: Annotated[
        Path | None,
        typer.Option("--board", help="The board recorded: written into the dataset as "
                     "board.yaml (calibrate reads it without --board); videos: keep only frames "
                     "where it is seen and still (see --still-px-s)."),
    ] = None,
    still_px_s: Annotated[
        float | None,
        typer.Option(help="Videos with --board: a view is still when its corners move at most "
                     "this many pixels per second (default 100)."),
    ] = None,
    step: Annotated[
        int, typer.Option(help="Videos without --board: keep every STEP-th frame set.")
    ] = 1,
    depth_model: Annotated[
        Path | None,
        typer.Option("--depth-model", help="Recordings: write each named camera's depth "
                     "corrected by its model in this depth_model.yaml (or calibrate output "
                     "folder); camera names as after --names."),
    ] = None,
) -> None:
    """Convert RealSense SDK recordings, ROS bags or one video per camera into the dataset
    folder form (videos: colour only, rig.yaml with the image sizes: intrinsics calibrated from
    scratch)."""
    from .console import cli_convert

    check_output_folder(out)
    board = None
    if board_file is not None:
        from ..model.board_file import load_board

        board = load_board(board_file)
    cli_convert(sources, out, name_list(names), sync_tolerance_ms, timestamps=timestamps,
                board=board, step=step, still_px_s=still_px_s, depth_models=depth_model)


@command()
@user_errors
def record(
    out: Annotated[Path, typer.Option("--out", help="Dataset folder to write.")],
    sets: Annotated[
        int | None, typer.Option(help="Stop after this many frame sets (default: until Ctrl-C).")
    ] = None,
    resolution: Annotated[str, typer.Option(help="WIDTHxHEIGHT of colour and depth.")] = "1280x720",
    fps: Annotated[int, typer.Option(help="Frame rate.")] = 30,
    hardware_sync: Annotated[
        bool, typer.Option(help="First camera master, others slaves (needs sync cables).")
    ] = False,
    board_file: Annotated[
        Path | None, typer.Option("--board", help="Board YAML for the live marker count.")
    ] = None,
    names: Annotated[
        str | None, typer.Option(help="Comma-separated camera names in serial order.")
    ] = None,
) -> None:
    """Record colour + aligned depth from connected D435i cameras (Ctrl-C stops)."""
    from ..model.board import thesis_board
    from ..model.board_file import load_board
    from .console import cli_record

    check_output_folder(out)
    w, h = parse_resolution(resolution)
    b = load_board(board_file) if board_file else thesis_board()
    cli_record(out, sets, (w, h, fps), hardware_sync, b, name_list(names))


if __name__ == "__main__":  # pragma: no cover
    app()
