"""Findings about where the board was held (coverage, distance, tilt), what the board views
support of the refined intrinsics and lens, and the self-calibrated back sheet
(:mod:`.findings` runs the rules)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .findings_base import Finding, cameras_of, finding
from .numbers import fmt
from .schema import (
    BOARD_SIZE_EXAMPLE,
    CORNER_REGIONS,
    COVERAGE_MIN,
    DISTANCE_SPREAD_MIN,
    EDGE_OFFSET_MIN_PX,
    EDGE_OFFSET_SIGMAS,
    EDGE_SIZE_MIN_PX,
    GLUE_MIN_DEG,
    GLUE_MIN_MM,
    GLUE_SIGMAS,
    INTRINSICS_SUPPORT_MAX,
    TILT_SPREAD_MIN_DEG,
)


def _placement(report: dict[str, Any], earlier: list[Finding]) -> list[tuple[str, Any]]:
    """The calibrated cameras not found inconsistent: those whose board placement counts."""
    inconsistent = cameras_of(earlier, "inconsistent_camera")
    return [
        (n, c) for n, c in report["cameras"].items() if c["calibrated"] and n not in inconsistent
    ]


def board_coverage(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    low = [
        (n, c["coverage"])
        for n, c in _placement(report, earlier)
        if c["coverage"]["image_fraction"] < COVERAGE_MIN and c["coverage"]["missing_regions"]
    ]
    if not low:
        return []
    regions: dict[str, int] = {}
    for _, cov in low:
        for r in cov["missing_regions"]:
            regions[r] = regions.get(r, 0) + 1
    common = sorted(regions, key=lambda r: -regions[r])[:3]
    return [
        finding(
            "info",
            "board_coverage",
            [n for n, _ in low],
            f"The board reached less than {COVERAGE_MIN:.0%} of the image of {len(low)} "
            "camera(s): "
            + ", ".join(f"{n} {cov['image_fraction']:.0%}" for n, cov in low)
            + ". Corners near the image border constrain the pose best.",
            "Next recording: also hold the board in the image regions it never reached "
            f"(most often: {', '.join(common)}; per camera in 'Where to put the board next').",
        )
    ]


def intrinsics_unsupported(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Refined intrinsics the data could not determine: the marginal sigma stays close to the
    prior's, so the 'refined' value is mostly the rig.yaml one (and its error)."""
    weak = {}
    for name, cam in report["cameras"].items():
        params = [
            p for p, e in (cam.get("intrinsics_refined") or {}).items()
            if e["sigma"] is not None and e["prior_sigma"]
            and e["sigma"] > INTRINSICS_SUPPORT_MAX * e["prior_sigma"]
        ]
        if params:
            weak[name] = params
    if not weak:
        return []
    return [
        finding(
            "warning",
            "intrinsics_unsupported",
            list(weak),
            "The board views hardly constrain some refined intrinsics (marginal sigma above "
            f"{INTRINSICS_SUPPORT_MAX:.0%} of the prior's): "
            + "; ".join(f"{n}: {' '.join(p)}" for n, p in weak.items())
            + ". Their refined values are mostly the starting ones (rig.yaml's, or the first "
            "estimate of a camera calibrated from scratch).",
            "Record more views with the board at several distances and tilts, reaching the "
            "image corners (distortion), or refine fewer parameters "
            "(bundle.intrinsics_params, e.g. fx fy cx cy).",
        )
    ]


def lens_coverage(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Refined lens distortion from views that covered little of the image, or never reached
    one of its corners: the polynomial is fitted where the board went and extrapolated
    elsewhere, most at the corners (measured: docs/report_schema.md, docs/accuracy.md)."""
    thin = {}
    for name, cam in report["cameras"].items():
        if cam.get("intrinsics_initial"):
            continue  # scratch_coverage says it for a camera calibrated from scratch
        refined = cam.get("intrinsics_refined") or {}
        cov = cam.get("coverage") or {}
        if not any(p not in ("fx", "fy", "cx", "cy") for p in refined) \
                or cov.get("image_fraction") is None:
            continue
        corners = [r for r in cov.get("missing_regions") or [] if r in CORNER_REGIONS]
        if cov["image_fraction"] < COVERAGE_MIN or corners:
            thin[name] = f"{cov['image_fraction']:.0%}" + (
                f", never the {' / '.join(corners)} corner" if corners else "")
    if not thin:
        return []
    return [
        finding(
            "warning",
            "lens_coverage",
            list(thin),
            "The lens distortion was refined from views covering little of the image or "
            "not reaching its corners (" + "; ".join(f"{n} {t}" for n, t in thin.items())
            + f"; {COVERAGE_MIN:.0%} and every corner wanted): the refined model "
            "(rig_refined.yaml) holds where the board went and is an extrapolation towards "
            "the image corners.",
            "Before using rig_refined.yaml's distortion for the whole image, record views with "
            "the board close to each camera, reaching its image corners, and calibrate again.",
        )
    ]


def scratch_coverage(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """A camera calibrated from scratch (rig.yaml gave only its size) whose board views
    reached little of the image: its focal length, centre and distortion rest on that part."""
    thin = {
        name: cam["intrinsics_initial"]
        for name, cam in report["cameras"].items()
        if cam.get("intrinsics_initial")
        and cam["intrinsics_initial"]["image_fraction"] < COVERAGE_MIN
    }
    if not thin:
        return []
    return [
        finding(
            "warning",
            "scratch_coverage",
            list(thin),
            "Intrinsics calibrated from scratch from views whose corners reached little of the "
            "image ("
            + ", ".join(f"{n} {i['image_fraction']:.0%} in {i['views']} views"
                        for n, i in thin.items())
            + f", under {COVERAGE_MIN:.0%}): the lens model (rig_refined.yaml) is fitted there "
            "and extrapolated elsewhere, and the focal length trades against the distances.",
            "Record more views with these cameras, the board reaching every image region and "
            "tilted, or give their intrinsics in rig.yaml.",
        )
    ]


def board_glue(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The back sheet off its board-file place (``bundle.board: refine``): significant against
    its sigma and large enough to matter; or held because it was unobservable."""
    refined = report["board"].get("refined")
    if not refined:
        return []
    if refined["held"]:
        return [finding("info", "board_glue", [], f"Board not refined: {refined['held']}.",
                        "To refine the back sheet, record views in which cameras on both "
                        "sides see the board at the same time.")]
    (dx, dy), rot = refined["offset_mm"], refined["rotation_deg"]
    (sx, sy), srot = refined["sigmas"]["offset_mm"], refined["sigmas"]["rotation_deg"]
    shifted = (abs(dx) > GLUE_SIGMAS * sx or abs(dy) > GLUE_SIGMAS * sy) and (
        np.hypot(dx, dy) > GLUE_MIN_MM)
    turned = abs(rot) > GLUE_SIGMAS * srot and abs(rot) > GLUE_MIN_DEG
    if not (shifted or turned):
        return []
    return [finding(
        "warning",
        "board_glue",
        [],
        f"{glue_sentence(refined)} (sigma {fmt(sx, 2)} / {fmt(sy, 2)} mm, {fmt(srot, 3)} deg).",
        "Use board_refined.yaml (--board) for the next calibrations with this board, or "
        "re-glue the back sheet.",
    )]


def board_size(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The board file states no ``print_scale_sigma``: its lengths are taken as exact, and
    every translation scales with the printed size. The images cannot see a print error (the
    whole rig scales with it), nor, below a percent, the cameras' depth, whose own scales
    differ by a few 0.1 % (a render printed 0.2 % large: every camera 0.2 % of its distance
    off, up to 6.0 mm at 3 m, at up to 13 of its sigmas; docs/accuracy.md)."""
    board = report.get("board") or {}
    if "print_scale_sigma" not in board or board["print_scale_sigma"] is not None:
        return []
    far = {n: float(np.linalg.norm(c["translation_m"])) for n, c in report["cameras"].items()
           if c.get("calibrated") and c.get("translation_m") is not None}
    if not far or max(far.values()) <= 0:
        return []
    cam = max(far, key=far.get)
    return [finding(
        "info",
        "board_size",
        [cam],
        f"Every translation scales with the printed board's size, which the board file gives "
        f"as exact (no print_scale_sigma): a print {100 * BOARD_SIZE_EXAMPLE:.1f} % off the "
        f"file puts {cam} {1000 * BOARD_SIZE_EXAMPLE * far[cam]:.1f} mm off ({far[cam]:.2f} m "
        "from the reference), which neither the images nor the cameras' depth can see.",
        "Measure the printed grid end to end (a steel rule or calipers over the outermost "
        "marker corners) and run `rgbd-calib board BOARD.yaml --measured ACROSS_MM DOWN_MM`: "
        "it writes the board file rescaled to the print, with the measurement's relative "
        "1 sigma as its print_scale_sigma, so the sigmas hold it; docs/formats.md.",
    )]


def glue_sentence(refined: dict[str, Any]) -> str:
    """'Back sheet is 1.50 mm right, 1.00 mm down, 0.30 deg counter-clockwise of where the
    board file puts it (seen from the front); thickness 6.60 mm (+0.00)' from
    ``report.board.refined``."""
    (dx, dy), rot = refined["offset_mm"], refined["rotation_deg"]
    return (
        f"Back sheet is {abs(dx):.2f} mm {'right' if dx >= 0 else 'left'}, "
        f"{abs(dy):.2f} mm {'up' if dy >= 0 else 'down'}, {abs(rot):.2f} deg "
        f"{'counter-clockwise' if rot >= 0 else 'clockwise'} of where the board file puts it "
        f"(seen from the front); thickness {refined['thickness_mm']:.2f} mm "
        f"({refined['thickness_change_mm']:+.2f})"
    )


def board_distance(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    narrow = [
        (n, c["coverage"]["distance_m"])
        for n, c in _placement(report, earlier)
        if c["coverage"]["distance_m"]
        and c["views_used"] >= 3
        and c["coverage"]["distance_m"]["max"]
        < DISTANCE_SPREAD_MIN * c["coverage"]["distance_m"]["min"]
    ]
    if not narrow:
        return []
    return [
        finding(
            "info",
            "board_distance",
            [n for n, _ in narrow],
            "The board was at one distance only for "
            + ", ".join(f"{n} ({d['min']:.2f}-{d['max']:.2f} m)" for n, d in narrow)
            + ".",
            "Also show the board nearer to and further from "
            + ", ".join(n for n, _ in narrow)
            + ".",
        )
    ]


def board_tilt(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    flat = [
        (n, c["coverage"]["tilt_deg"])
        for n, c in _placement(report, earlier)
        if c["coverage"]["tilt_deg"]
        and c["views_used"] >= 3
        and c["coverage"]["tilt_deg"]["max"] - c["coverage"]["tilt_deg"]["min"]
        < TILT_SPREAD_MIN_DEG
    ]
    if not flat:
        return []
    return [
        finding(
            "info",
            "board_tilt",
            [n for n, _ in flat],
            "The board's tilt barely varied for "
            + ", ".join(f"{n} ({t['min']:.0f}-{t['max']:.0f} deg)" for n, t in flat)
            + ".",
            "Tilt the board 20-50 deg in different directions in front of "
            + ", ".join(n for n, _ in flat)
            + ".",
        )
    ]


def edge_offset(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Cameras whose markers read larger or smaller than the board's geometry
    (``bundle.edge_offset``): a detector edge offset (ink spread, blur, the camera's
    sharpening). Taken out of the corners (``applied_px``), it is named as information; what
    no model holds (``bundle.edge_offset: off``, or a reading too weak to model) biases every
    board pose of the camera: a warning; so does what grows with the markers' size beyond the
    offset (``size_mm``, ``size_effect_px``): the warning ``edge_size``."""
    offsets = (report.get("bundle") or {}).get("edge_offset") or {}

    def listed(rows: list[tuple[str, dict[str, Any]]], key: str) -> str:
        return ", ".join(f"{c} {e[key]:+.3f} px (+-{e['sigma_px']:.3f}, {e['markers']} markers)"
                         for c, e in rows)

    modelled = [(c, e) for c, e in sorted(offsets.items()) if e.get("applied_px")]
    off = [(c, {**e, "residual": e["offset_px"] - e.get("applied_px", 0.0)})
           for c, e in sorted(offsets.items())]
    off = [(c, e) for c, e in off if abs(e["residual"]) >= EDGE_OFFSET_MIN_PX
           and abs(e["residual"]) >= EDGE_OFFSET_SIGMAS * e["sigma_px"]]
    out = []
    if modelled:
        out.append(finding(
            "info",
            "edge_offset",
            [c for c, _ in modelled],
            "The markers read larger (+) or smaller (-) than the board's geometry, per edge: "
            + listed(modelled, "offset_px")
            + ". Modelled: taken out of these cameras' corners before the solve (bundle."
            "edge_offset: auto); unmodelled it would have moved their extrinsics by about "
            "18 mm per px.",
            "Nothing to do for the extrinsics. An offset above 0.1 px usually means blur or "
            "in-camera sharpening: sharpen the focus or turn the sharpening down for the "
            "next recording.",
        ))
    if off:
        out.append(finding(
            "warning",
            "edge_offset",
            [c for c, _ in off],
            "The markers read larger (+) or smaller (-) than the board's geometry, per edge, "
            "beyond any model: " + listed(off, "residual")
            + ". Such an edge offset moves the extrinsics by about 18 mm per px on the race "
            "and ring renders and their sigmas do not include it.",
            "Set bundle.edge_offset: auto (the default) to model it, or expect the named "
            "cameras' extrinsics off by roughly 18 mm x the offset (docs/accuracy.md, 'A "
            "detector's edge offset'); sharpen the focus, turn the camera's sharpening down, "
            "or print the board with less ink spread, and calibrate again.",
        ))
    sized = [(c, e) for c, e in sorted(offsets.items())
             if abs(e.get("size_effect_px", 0.0)) >= EDGE_SIZE_MIN_PX
             and abs(e.get("size_mm", 0.0)) >= EDGE_OFFSET_SIGMAS * e.get("size_sigma_mm", 0.0)]
    if sized:
        out.append(finding(
            "warning",
            "edge_size",
            [c for c, _ in sized],
            "The markers' edge bias grows with their size in the image beyond the modelled "
            "offset: " + ", ".join(
                f"{c} as an ink spread of {e['size_mm']:+.3f} mm (+-{e['size_sigma_mm']:.3f}; "
                f"its near markers {e['size_effect_px']:+.3f} px per edge off its far ones)"
                for c, e in sized)
            + ". Not modelled: on renders a print's ink spread of 0.25 mm left 0.28 mm in the "
            "extrinsics (about their sigmas), 0.5 mm left 0.65 mm (2.2 times their sigmas).",
            "Expect the named cameras' extrinsics off by a few tenths of a millimetre more than "
            "their sigmas say; print the board on a laser printer on matte paper (less ink "
            "spread), sharpen the focus or turn the camera's sharpening down, and calibrate "
            "again (docs/accuracy.md, 'A detector's edge offset').",
        ))
    return out
