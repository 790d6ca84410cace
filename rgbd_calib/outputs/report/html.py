"""The report page: one self-contained, offline HTML string (figures as base64 PNG, the
3D viewer inline), assembled from one function per section, each returning its chunks.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ...core.progress import Progress, Tick, start
from ...solve.pose import DROP_ADVICE
from .cloud import Cloud, load_cloud
from .figures import palette, render_figures
from .findings_base import ranked_actionable
from .layout import display_frame
from .numbers import percent_of_prior
from .viewer import VIEWER_JS, viewer_data

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;color:#1d2330;
background:#f4f5f7}
main{max-width:1180px;margin:0 auto;padding:18px 24px 60px}
h1{font-size:24px;margin:8px 0 2px}h2{font-size:18px;margin:30px 0 8px;border-bottom:2px solid
#d9dce3;padding-bottom:4px}.sub{color:#5b6475;font-size:13px}
section{background:#fff;border-radius:8px;padding:6px 18px 14px;margin:14px 0;
box-shadow:0 1px 2px rgba(0,0,0,.08)}
table{border-collapse:collapse;font-size:12.5px;margin:6px 0}th,td{padding:3px 7px;
border-bottom:1px solid #e3e5ea;text-align:right;white-space:nowrap}th{white-space:normal;
vertical-align:bottom}.scroll{overflow-x:auto}
.l{text-align:left;white-space:normal}th{background:#f0f2f5;
font-weight:600}td:first-child,th:first-child{text-align:left}
.verdict{display:inline-block;padding:3px 12px;border-radius:14px;font-weight:700;
color:#fff;margin-left:8px;font-size:15px;vertical-align:middle}
.good{background:#2e8b57}.check{background:#d08a00}.poor{background:#c0392b}
.w{border-left:5px solid;padding:6px 10px;margin:6px 0;border-radius:4px;background:#fafbfc}
.w.error{border-color:#c0392b}.w.warning{border-color:#d08a00}.w.info{border-color:#5b7db1}
.w b.sev{text-transform:uppercase;font-size:11px;margin-right:6px}
.w .adv{color:#3b4252;margin-top:2px}.bad{color:#c0392b;font-weight:600}
img.fig{max-width:100%;height:auto;display:block;margin:6px 0}
.cap{color:#5b6475;font-size:12.5px;margin:2px 0 8px}
#viewer{width:100%;height:560px;background:#11151c;border-radius:6px;cursor:grab;display:block}
.legend span{display:inline-block;margin:2px 10px 2px 0;font-size:12.5px}
.legend i{display:inline-block;width:11px;height:11px;border-radius:2px;margin-right:4px;
vertical-align:-1px}button{font:inherit;font-size:12.5px;padding:3px 10px;margin:4px 6px 4px 0;
border:1px solid #b8bfcc;background:#fff;border-radius:4px;cursor:pointer}
details{margin:6px 0}code{font-size:12.5px}ol li{margin:3px 0}
.actions .why{color:#3b4252;font-size:13px}
"""

_JS_GUARD = """
(function(){var b=document.documentElement;function add(m){b.dataset.jsErrors=
(b.dataset.jsErrors||'')+m+'\\n';}window.addEventListener('error',function(e){add(e.message||
'resource error');},true);window.addEventListener('unhandledrejection',function(e){add(
String(e.reason));});})();
"""

_JS_READY = """
(function(){function check(){var imgs=Array.prototype.slice.call(document.images),
done=imgs.every(function(i){return i.complete;}),cv=document.getElementById('viewer');
if(!done||!cv||cv.dataset.ready!=='yes'){return setTimeout(check,50);}
var broken=imgs.filter(function(i){return !(i.naturalWidth>0);}).length,b=document.body;
b.dataset.images=imgs.length;b.dataset.brokenImages=broken;
b.dataset.reportReady=broken===0?'yes':'broken';}
if(document.readyState==='complete')check();else window.addEventListener('load',check);})();
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(x: float | None, digits: int = 3, unit: str = "") -> str:
    if x is None:
        return '<span class="sub">n/a</span>'
    text = f"{x:.{digits}f}"
    return (text.lstrip("-") if float(text) == 0 else text) + unit


def _img(b64: str, alt: str) -> str:
    return f'<img class="fig" alt="{_e(alt)}" src="data:image/png;base64,{b64}">'


def _table(headers: Sequence[str], rows: Sequence[Sequence[str]], left: Sequence[int] = ()) -> str:
    """An HTML table; columns in ``left`` are left-aligned text."""

    def cell(tag: str, k: int, c: str) -> str:
        return f"<{tag} class='l'>{c}</{tag}>" if k in left else f"<{tag}>{c}</{tag}>"

    head = "".join(cell("th", k, h) for k, h in enumerate(headers))
    body = "".join(
        "<tr>" + "".join(cell("td", k, c) for k, c in enumerate(r)) + "</tr>" for r in rows
    )
    return (
        f"<div class='scroll'><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody>"
        "</table></div>"
    )


Figures = dict[str, str | None]


def _swatch(color: tuple[float, float, float]) -> str:
    return f"rgb{tuple(int(255 * v) for v in color)}"


def _head(report: dict[str, Any]) -> list[str]:
    ds, summ = report["dataset"], report["summary"]
    return [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width,initial-scale=1'>"
        f"<title>rgbd-calib report: {_e(ds.get('path') or '')}</title>"
        f"<style>{_CSS}</style><script>{_JS_GUARD}</script></head><body><main>",
        f"<h1>{'Depth-only refinement' if _depth_only(report) else 'Calibration'} report "
        f"<span class='verdict {summ['verdict']}'>{_e(summ['verdict'].upper())}</span></h1>",
        *_refine_head(report),
        f"<div class='sub'>dataset <code>{_e(ds.get('path'))}</code> &middot; method "
        f"<b>{_e(report['method'])}</b> &middot; reference camera <b>{_e(report['reference'])}"
        f"</b> (world frame = its colour optical frame: x right, y down, z forward) &middot; "
        f"rgbd-calib {_e(report['rgbd_calib_version'])}, report schema "
        f"{_e(report['schema_version'])}</div>",
    ]


def _depth_only(report: dict[str, Any]) -> bool:
    """A report of ``rgbd-calib refine`` (method ``depth``): no board result."""
    return report.get("refine") is not None


def _refine_head(report: dict[str, Any]) -> list[str]:
    """The line saying what a depth-only refinement is and where it started."""
    if not _depth_only(report):
        return []
    ref = report["refine"]
    what = ("only the cameras found moved since it were re-registered (--fix-others)"
            if ref["fix_others"] else "every overlapping camera pair registered")
    return [
        f"<p><b>Depth-only refinement</b> ({_e(ref['registration'])}) starting from "
        f"<code>{_e(ref['init'])}</code>: {what}. No board was used, so the board sections "
        f"of a calibration report (views, markers, reprojection, coverage) are empty. "
        f"Outcome <b>{_e(ref['outcome'])}</b>: {_e(ref['message'])}.</p>"
    ]


REPORT_ACTIONS = 3  # the actions the report leads with, as the console does


def _verdict_section(report: dict[str, Any]) -> list[str]:
    """The verdict in plain words, then at most :data:`REPORT_ACTIONS` actions (the ranked
    actionable findings, as the console lists them: what to do, then why), then every
    finding folded."""
    out = ["<section><h2>Verdict and what to do next</h2>"]
    verdict_text = {
        "good": "No camera or view needs attention: these extrinsics can be used.",
        "check": "Usable, but some cameras or views need a look (below).",
        "poor": "Do not use these extrinsics as they are: do what is listed below and re-run.",
    }[report["summary"]["verdict"]]
    out.append(f"<p><b>{verdict_text}</b></p>")
    actions = ranked_actionable(report["warnings"])[:REPORT_ACTIONS]
    if actions:
        out.append("<h3>What to do</h3><ol class='actions'>" + "".join(
            f"<li><b>{_e(w['advice'])}</b><div class='why'>{_e(w['severity'])} "
            f"<code>{_e(w['code'])}</code>"
            + (f" [{_e(', '.join(w['cameras']))}]" if w.get("cameras") else "")
            + f": {_e(w['message'])}</div></li>" for w in actions) + "</ol>")
    findings = [
        f"<div class='w {w['severity']}'><b class='sev'>{w['severity']}</b>"
        f"<code>{_e(w['code'])}</code> {_e(w['message'])}"
        + (f"<div class='adv'>&rarr; {_e(w['advice'])}</div>" if w["advice"] else "")
        + "</div>"
        for w in report["warnings"]]
    if findings:
        out.append(f"<details><summary>Every finding ({len(findings)})</summary>"
                   + "".join(findings) + "</details>")
    else:
        out.append("<p>No warnings.</p>")
    if report["next_steps"]:
        out.append(
            "<h3>Next steps, in order</h3><ol>"
            + "".join(f"<li>{_e(s)}</li>" for s in report["next_steps"])
            + "</ol>"
        )
    out.append("</section>")
    return out


def _summary_rows(report: dict[str, Any]) -> list[tuple[str, Any, str]]:
    """(quantity, value, unit) rows of the summary table."""
    summ = report["summary"]
    worst_r, worst_t = summ["worst_sigma_rotation_deg"], summ["worst_sigma_translation_mm"]
    rows = [
        ("cameras calibrated", f"{summ['n_calibrated']} / {summ['n_cameras']}", ""),
        ("frame sets", summ["n_frames"], ""),
        ("board poses (views of the board)", summ["n_board_views"], ""),
        ("camera views used / dropped", f"{summ['n_views_used']} / {summ['n_views_dropped']}", ""),
        ("markers used / excluded", f"{summ['n_markers_used']} / {summ['n_markers_excluded']}", ""),
        ("pose-graph outlier views", summ["n_outlier_edges"], ""),
        ("reprojection RMS, whole rig", _num(summ["reprojection_rms_px"], 3), "px"),
        (
            "median camera reprojection RMS",
            _num(summ["median_camera_reprojection_rms_px"], 3),
            "px",
        ),
        (
            "median 1-sigma rotation / translation",
            f"{_num(summ['median_sigma_rotation_deg'], 4)} / "
            f"{_num(summ['median_sigma_translation_mm'], 3)}",
            "deg / mm",
        ),
        (
            "worst 1-sigma rotation",
            (f"{worst_r['value']:.4f} ({_e(worst_r['camera'])})" if worst_r else "n/a"),
            "deg",
        ),
        (
            "worst 1-sigma translation",
            (f"{worst_t['value']:.3f} ({_e(worst_t['camera'])})" if worst_t else "n/a"),
            "mm",
        ),
        (
            "median edge residual translation / rotation",
            f"{_num(summ['median_edge_translation_mm'], 3)} / "
            f"{_num(summ['median_edge_rotation_deg'], 4)}",
            "mm / deg",
        ),
    ]
    if "bundle" in report:
        rows.append(
            (
                "bundle: corner noise estimated",
                _num(report["bundle"]["pixel_sigma_estimated"], 3),
                "px",
            )
        )
        ladder = report["bundle"].get("self_calibration")
        if ladder:
            tried = "; ".join(
                f"{lv['level']}: {'kept' if lv['accepted'] else 'not kept'}"
                for lv in ladder["levels"][1:]
            )
            rows.append(
                (
                    "self-calibration: model chosen",
                    ladder["chosen"] + (" (markers detected again)" if ladder["redetected"]
                                        else ""),
                    f"tried {tried}" if tried else "",
                )
            )
    return rows


def _camera_row(
    report: dict[str, Any], name: str, color: tuple[float, float, float], flagged: set[str]
) -> list[str]:
    """One row of the cameras table (camera names with an error or warning in red)."""
    c = report["cameras"][name]
    rep, t = c["reprojection_all_px"] or {}, c["translation_m"] or [None] * 3
    cov = c["coverage"]
    d = cov["distance_m"]
    sw = (
        "<i style='display:inline-block;width:10px;height:10px;margin-right:5px;"
        f"background:{_swatch(color)}'></i>"
    )
    label = f"<span class='bad'>{_e(name)}</span>" if name in flagged else _e(name)
    return [
        sw + label + (" (ref)" if name == report["reference"] else ""),
        "yes" if c["calibrated"] else "<span class='bad'>no</span>",
        f"{c['views_used']} / {c['views_dropped']}",
        str(c["edge_outliers"]),
        _num(rep.get("p50"), 3),
        _num(rep.get("p90"), 3),
        _num(c["sigma_rotation_deg"], 4),
        _num(c["sigma_translation_mm"], 3),
        " ".join(_num(v, 3) for v in t),
        f"{d['min']:.2f}-{d['max']:.2f}" if d else "n/a",
        f"{cov['faces']['front']}/{cov['faces']['back']}",
        f"{cov['image_fraction']:.0%}",
        _num(c["depth_scale_factor"], 4),
    ]


def _depth_only_summary(report: dict[str, Any], colors: list, flagged: set[str]) -> list[str]:
    """Summary and cameras tables of a depth-only refinement: pairs, sigmas, each camera's
    move from the initial extrinsics and its depth-scale factor and source."""
    summ, ref, pairs = report["summary"], report["refine"], report["pairs"]
    worst_t = summ["worst_sigma_translation_mm"]
    rows = [
        ("cameras with extrinsics", f"{summ['n_calibrated']} / {summ['n_cameras']}", ""),
        ("frame sets", summ["n_frames"], ""),
        ("camera pairs accepted / registered",
         f"{sum(bool(p['accepted']) for p in pairs)} / {len(pairs)}", ""),
        ("median 1-sigma rotation / translation",
         f"{_num(summ['median_sigma_rotation_deg'], 4)} / "
         f"{_num(summ['median_sigma_translation_mm'], 3)}", "deg / mm"),
        ("worst 1-sigma translation",
         f"{worst_t['value']:.3f} ({_e(worst_t['camera'])})" if worst_t else "n/a", "mm"),
        ("depth stage", _e(report["depth"]["status"]), _e(report["depth"]["reason"] or "")),
    ]
    cam_rows = []
    for i, (name, c) in enumerate(report["cameras"].items()):
        m = ref["cameras"].get(name) or {}
        label = f"<span class='bad'>{_e(name)}</span>" if name in flagged else _e(name)
        cam_rows.append([
            "<i style='display:inline-block;width:10px;height:10px;margin-right:5px;"
            f"background:{_swatch(colors[i])}'></i>" + label
            + (" (ref)" if name == report["reference"] else ""),
            "yes" if c["calibrated"] else "<span class='bad'>no</span>",
            _num(c["sigma_rotation_deg"], 4),
            _num(c["sigma_translation_mm"], 3),
            " ".join(_num(v, 3) for v in c["translation_m"] or [None] * 3),
            f"{_num(m.get('moved_mm'), 2)} / {_num(m.get('moved_deg'), 3)}",
            _num(m.get("initial_sigma_mm"), 3),
            _num(c["depth_scale_factor"], 4),
            _e(m.get("depth_scale_source", "-")),
        ])
    return [
        "<section><h2>Summary</h2>"
        + _table(["quantity", "value", "unit"], [(a, str(b), c) for a, b, c in rows]),
        "<h3>Cameras</h3>"
        + _table(["camera", "has extrinsics", "&sigma; rot (deg)", "&sigma; trans (mm)",
                  "x y z (m)", "moved from --init (mm / deg)", "initial &sigma; trans (mm)",
                  "depth scale factor", "scale from"], cam_rows, left=(8,)),
        "<p class='cap'>&sigma;: 1-sigma marginal uncertainty of T_ref_cam (largest single "
        "axis) after the refinement. Moved: from the --init extrinsics. Depth scale: measured / "
        "true depth; from <i>given</i> (the report.json next to --init), <i>board</i> "
        "(estimated from the board in view), <i>unknown</i> (the camera's pairs were not "
        "allowed to move it along what a scale error explains) or <i>none</i> (no depth "
        "cloud).</p></section>",
    ]


def _summary_section(report: dict[str, Any], colors: list) -> list[str]:
    """The summary table and the cameras table."""
    flagged = {c for w in report["warnings"] if w["severity"] != "info" for c in w["cameras"]}
    if _depth_only(report):
        return _depth_only_summary(report, colors, flagged)
    rows = _summary_rows(report)
    cam_rows = [
        _camera_row(report, name, colors[i], flagged) for i, name in enumerate(report["cameras"])
    ]
    return [
        "<section><h2>Summary</h2>"
        + _table(["quantity", "value", "unit"], [(a, str(b), c) for a, b, c in rows]),
        "<h3>Cameras</h3>"
        + _table(
            [
                "camera",
                "calibrated",
                "views used / dropped",
                "outlier views",
                "reproj. p50 (px)",
                "reproj. p90 (px)",
                "&sigma; rot (deg)",
                "&sigma; trans (mm)",
                "x y z (m)",
                "board dist. (m)",
                "faces front/back",
                "image covered",
                "depth scale factor",
            ],
            cam_rows,
        ),
        "<p class='cap'>Reprojection: RMS over each marker's 4 corners of the board corners "
        "projected through the final camera and board poses, over all of the camera's views "
        "(also the excluded ones). &sigma;: 1-sigma marginal uncertainty of T_ref_cam "
        "(largest single axis). Depth scale factor: measured / true depth (depth stage; n/a "
        "until it runs).</p></section>",
    ]


def _rig_section(figs: Figures) -> list[str]:
    return [
        "<section><h2>Rig layout</h2>" + _img(figs["rig"], "top and side views of the rig"),
        "<p class='cap'>Camera frusta (reference camera in red) and every board pose (grey "
        "outlines; RGB axes = board x, y, z for a subset, as in the thesis's Figure 4.11). "
        "Axes: <i>up</i> = minus the cameras' mean image-down direction, <i>e1</i> = the "
        "horizontal direction along which the cameras spread most, e2 = up &times; e1.</p>"
        "</section>",
    ]


def _viewer_section(
    report: dict[str, Any], colors: list, cloud: Cloud | None, no_cloud_reason: str
) -> list[str]:
    return [
        "<section><h2>3D view</h2><div><button id='v-home'>reset</button><button id='v-top'>"
        "top</button><button id='v-side'>side</button><button id='v-color'>colour: camera / "
        "RGB</button><button id='v-boards'>board poses on/off</button> <span class='sub'>"
        "drag to orbit, scroll to zoom</span></div><canvas id='viewer'></canvas>"
        "<div class='legend'>"
        + "".join(
            f"<span><i style='background:{_swatch(colors[i])}'></i>{_e(n)}</span>"
            for i, n in enumerate(report["cameras"])
        )
        + "</div>",
        f"<p class='cap'>{_e(cloud.source) if cloud else 'No point cloud: ' + _e(no_cloud_reason)}"
        "</p></section>",
    ]


def _cloud_section(figs: Figures, cloud: Cloud | None, no_cloud_reason: str) -> list[str]:
    out = ["<section><h2>Fused cloud</h2>"]
    if figs["cloud"]:
        out.append(_img(figs["cloud"], "fused point cloud, top and side views"))
        out.append(
            "<p class='cap'>Coloured by camera: where two colours meet, the cameras agree if the "
            "surfaces coincide (a doubled wall or floor means an extrinsic or depth-scale "
            "error). " + _e(cloud.source if cloud else "") + "</p>"
        )
    else:
        out.append(f"<p><b>No depth</b>: {_e(no_cloud_reason)}.</p>")
    out.append("</section>")
    return out


def _intrinsics_section(report: dict[str, Any]) -> list[str]:
    """Refined intrinsics (``bundle.intrinsics: refine``): each parameter against its prior
    (rig.yaml's, or the first estimate from scratch); nothing when the intrinsics were held
    fixed."""
    rows = []
    for name, cam in report["cameras"].items():
        for param, e in (cam.get("intrinsics_refined") or {}).items():
            unit = "px" if param in ("fx", "fy", "cx", "cy") else ""

            def num(x: float | None, unit: str = unit) -> str:
                return "-" if x is None else f"{x:.6g}{' ' + unit if unit else ''}"

            pct = percent_of_prior(e["prior"], e["change"])
            rows.append((_e(name), param, num(e["prior"]), num(e["refined"]), num(e["change"]),
                         "-" if pct is None else f"{pct:+.3f} %", num(e["sigma"]),
                         num(e["prior_sigma"])))
    if not rows:
        return []
    return [
        "<section><h2>Refined intrinsics</h2>"
        + _table(["camera", "parameter", "prior", "refined", "change", "change % of prior",
                  "sigma", "prior sigma"], rows, left=(0, 1)),
        "<p class='cap'>The bundle adjustment refined these parameters from a prior: the "
        "rig.yaml value, or for a camera whose rig.yaml gives only its image size, the first "
        "estimate from scratch from its own views (sigma: the estimate's marginal 1-sigma); "
        "the refined models are in rig_refined.yaml. The change in percent only where the "
        "prior is a base for it (not about zero, not outgrown by the change). A sigma close "
        "to the prior's means the views hardly constrained that parameter.</p></section>",
    ]


def _residual_sections(figs: Figures) -> list[str]:
    """Reprojection histograms, residual by edge and co-visibility: a figure and a caption
    each."""
    return [
        "<section><h2>Reprojection error per camera</h2>"
        + _img(figs["hist"], "per-camera reprojection error histograms"),
        "<p class='cap'>Per-marker RMS reprojection error (px) through the calibrated poses. "
        "Black: the camera's median (solid) and 90th percentile (dotted) over used markers; "
        "grey dashed: the rig's median camera; grey bars: markers the estimate excluded (outlier "
        "views or markers). A camera whose histogram sits right of the others has wrong "
        "intrinsics, blur or sync problems.</p></section>",
        "<section><h2>Residual by edge</h2>" + _img(figs["edges"], "residual by edge"),
        "<p class='cap'>Each pose-graph edge is one camera seeing one board pose (as in the "
        "thesis's Figure 5.2). Top: translation and rotation between the measured board pose "
        "(PnP) and the calibrated prediction; bottom: that view's final reprojection RMS. "
        "Red crosses: outlier or stale edges left out of the estimate.</p></section>",
        "<section><h2>Co-visibility</h2>" + _img(figs["covis"], "co-visibility matrix"),
        "<p class='cap'>Number of board poses two cameras both contributed to the estimate; a "
        "camera tied to the rest by few shared views is weakly constrained.</p></section>",
    ]


def _coverage_section(report: dict[str, Any], figs: Figures) -> list[str]:
    """Board coverage figures and the 'where to put the board next' table."""
    next_rows = []
    for name, cam in report["cameras"].items():
        cov = cam["coverage"]
        d, t = cov["distance_m"], cov["tilt_deg"]
        next_rows.append(
            [
                _e(name),
                f"{cov['image_fraction']:.0%}",
                _e(", ".join(cov["missing_regions"]) or "none"),
                f"{d['min']:.2f}-{d['max']:.2f}" if d else "n/a",
                f"{t['min']:.0f}-{t['max']:.0f}" if t else "n/a",
                f"{cov['faces']['front']} / {cov['faces']['back']}",
                f"{cov['max_shared_views']} ({_e(cov['best_partner'] or '-')})",
            ]
        )
    return [
        "<section><h2>Board coverage</h2>"
        + _img(figs["coverage"], "board coverage per camera")
        + _img(figs["distance"], "board distance and tilt per camera"),
        "<p class='cap'>Where the board was in each image (number of used views whose marker "
        "bounding box covers each spot; grey = never), and its distance and tilt. Good sets "
        "cover the whole image, several distances and tilts of 20-50 degrees.</p>",
        "<h3>Where to put the board next</h3>"
        + _table(
            [
                "camera",
                "image covered",
                "image regions never reached",
                "distance (m)",
                "tilt (deg)",
                "views front / back face",
                "most views shared with",
            ],
            next_rows,
            left=(2,),
        )
        + "</section>",
    ]


def _markers_section(figs: Figures) -> list[str]:
    return [
        "<section><h2>Markers</h2>" + _img(figs["markers"], "reprojection error per marker"),
        "<p class='cap'>A single marker far above the dashed median is misplaced, bent or "
        "peeling.</p></section>",
    ]


def _pairs_section(report: dict[str, Any], figs: Figures) -> list[str]:
    out = ["<section><h2>Camera pairs (depth)</h2>"]
    if not report["pairs"]:
        out.append(
            "<p>No camera pairs: the depth stage (pairwise ICP and overlap error maps) did not "
            "run for this result.</p>"
        )
    else:
        out.append(
            _table(
                [
                    "pair",
                    "overlap",
                    "ICP fitness",
                    "RMSE before (mm)",
                    "RMSE after (mm)",
                    "RMSE final (mm)",
                    "correction (deg / mm)",
                    "accepted",
                ],
                [
                    [
                        f"{_e(p['cam_a'])} &ndash; {_e(p['cam_b'])}",
                        _num(p["overlap_fraction"], 2),
                        _num(p["fitness"], 2),
                        _num(p["rmse_before_mm"], 2),
                        _num(p["rmse_after_mm"], 2),
                        _num(p["rmse_final_mm"], 2),
                        f"{_num(p['correction_deg'], 3)} / {_num(p['correction_mm'], 2)}",
                        {True: "yes", False: "no"}.get(p["accepted"], "n/a")
                        + (f": {_e(p['reason'])}" if p["reason"] else ""),
                    ]
                    for p in report["pairs"]
                ],
                left=(7,),
            )
        )
        if figs["errmap"]:
            out.append(
                _img(figs["errmap"], "overlap error maps")
                + "<p class='cap'>Overlap error maps: point-to-plane distance (mm) of camera a's "
                "points to camera b's surface, over a's image; a ramp across the map is a "
                "rotation error, a uniform offset a depth-scale or translation error.</p>"
            )
    out.append("</section>")
    return out


def _fused_section(report: dict[str, Any]) -> list[str]:
    """The fused cloud's quality: each camera's depth model and its board-plane residuals,
    each overlapping pair's signed surface distances before and after the models."""
    models, agree = report.get("depth_models") or {}, report.get("fused_agreement")
    if not models and not agree:
        return []
    out = ["<section><h2>Fused cloud (depth models)</h2>"]
    if models:
        rows = []
        for c, m in models.items():
            bands = m["bands"]
            worst = (max(bands, key=lambda b: abs(b["median_before_mm"])) if bands else None)
            rows.append([
                _e(c), _e(" + ".join(m["terms"]) or "identity"),
                ", ".join(f"{_e(k)} {v:.4g} &plusmn; {m['sigmas'].get(k, 0.0):.2g}"
                          for k, v in m["parameters"].items()) or "&ndash;",
                *((_num(max(abs(b["median_before_mm"]) for b in bands), 2),
                   _num(max(abs(b["median_after_mm"]) for b in bands), 2),
                   f"{_num(worst['z_min_m'], 2)}&ndash;{_num(worst['z_max_m'], 2)}")
                  if worst else ("n/a", "n/a", "n/a"))])
        out.append(_table(["camera", "terms chosen", "parameters &plusmn; 1 sigma",
                           "board-plane bias before (mm, worst band)",
                           "after (mm, worst band)", "worst band (m)"], rows, left=(1, 2)))
        out.append("<p class='cap'>Each camera's depth model, fitted on every depth pixel of "
                   "the board (depth_model.yaml); a term is kept only when the data support it. "
                   "Board-plane bias: median signed distance of the depth on the board face to "
                   "the face the colour solve put there, per distance band.</p>")
    if agree and agree["pairs"]:
        bias = agree.get("camera_bias_mm") or {}
        rows = [[f"{_e(p['cam_a'])} &ndash; {_e(p['cam_b'])}",
                 _num(p["before"]["median_mm"], 2) if p["before"] else "&ndash;",
                 f"{_num(p['after']['median_mm'], 2)} &plusmn; "
                 f"{_num(p['after']['median_se_mm'], 2)}",
                 _num(p["after"]["p90_mm"], 1), _num(p["noise_p90_mm"], 1),
                 "off" if p["off"] else "agrees"] for p in agree["pairs"]]
        out.append(_table(["pair", "bias before models (mm)", "bias after (mm)",
                           "p90 |distance| after (mm)", "p90 the noise predicts (mm)",
                           "beyond the noise"], rows))
        if bias:
            out.append(_table(["camera", "depth bias against the rig (mm)"],
                              [[_e(c), _num(v, 2)] for c, v in sorted(bias.items())]))
        out.append("<p class='cap'>Signed surface distance of camera a's points to camera b's "
                   "surface where they overlap in fused.ply (+: a's depth beyond b's). A pair "
                   "is off when its bias is beyond 1 mm and 3 of its standard errors; each "
                   "camera's bias is solved from all pairs, the median camera at 0.</p>")
    out.append("</section>")
    return out


def _dropped_tables(report: dict[str, Any], reasons: list[str]) -> list[str]:
    """Dropped views per camera and reason, the advice per reason, every dropped view."""
    dropped = report["dropped_views"]
    counts = [
        [_e(n)]
        + [str(sum(1 for d in dropped if d["camera"] == n and d["reason"] == r)) for r in reasons]
        for n in report["cameras"]
    ]
    return [
        _table(["camera"] + [_e(r) for r in reasons], counts),
        "<ul>"
        + "".join(f"<li><code>{_e(r)}</code>: {_e(DROP_ADVICE.get(r, ''))}</li>" for r in reasons)
        + "</ul>",
        "<details><summary>every dropped view</summary>"
        + _table(
            ["camera", "frame", "reason", "markers", "detail"],
            [
                [
                    _e(d["camera"]),
                    _e(d["frame"]),
                    _e(d["reason"]),
                    str(d["markers"]),
                    _e(d["detail"]),
                ]
                for d in dropped
            ],
            left=(2, 4),
        )
        + "</details>",
    ]


def _dropped_section(report: dict[str, Any]) -> list[str]:
    """Dropped views and the pose graph's outlier views."""
    out = ["<section><h2>Dropped views</h2>"]
    reasons = sorted({d["reason"] for d in report["dropped_views"]})
    out += _dropped_tables(report, reasons) if reasons else ["<p>No view was dropped.</p>"]
    if report["pose_graph"]["outliers"]:
        out.append(
            "<h3>Outlier views (pose graph)</h3>"
            + _table(
                ["camera", "frame", "whitened residual"],
                [
                    [_e(o["camera"]), _e(o["view"]), f"{o['whitened_norm']:.1f}"]
                    for o in report["pose_graph"]["outliers"]
                ],
            )
        )
    out.append("</section>")
    return out


def _footer(report: dict[str, Any], cloud: Cloud | None, frame: np.ndarray) -> list[str]:
    """The rebuild note, the viewer's data and the page's scripts."""
    return [
        "<p class='sub'>Rebuild this page from the saved folder with <code>rgbd-calib report "
        "DIR</code>; every number above is in <code>report.json</code> (schema "
        f"{_e(report['schema_version'])}, docs/report_schema.md).</p></main>",
        f"<script type='application/json' id='viewer-data'>"
        f"{viewer_data(report, cloud, frame)}</script>",
        f"<script>{VIEWER_JS}</script><script>{_JS_READY}</script></body></html>",
    ]


def render_html(
    report: dict[str, Any],
    cloud: Cloud | None,
    no_cloud_reason: str = "",
    tick: Tick | None = None,
) -> str:
    """The report page: one self-contained HTML string (figures as base64 PNG, inline JS)."""
    tick = tick or (lambda n=1: None)
    frame = display_frame(report)
    figs = render_figures(report, cloud, frame, tick)
    colors = palette(report)
    board = not _depth_only(report)  # the board sections need a board result
    sections = (
        _head(report),
        _verdict_section(report),
        _summary_section(report, colors),
        _intrinsics_section(report),
        _rig_section(figs),
        _viewer_section(report, colors, cloud, no_cloud_reason),
        _cloud_section(figs, cloud, no_cloud_reason),
        _residual_sections(figs) if board else [],
        _coverage_section(report, figs) if board else [],
        _markers_section(figs) if board else [],
        _pairs_section(report, figs),
        _fused_section(report),
        _dropped_section(report) if board else [],
        _footer(report, cloud, frame),
    )
    return "\n".join(chunk for section in sections for chunk in section)


def write_report_html(
    report: dict[str, Any], folder: Path, progress: Progress | None = None
) -> Path:
    """Write ``folder/report.html`` for a finalized report (cloud: ``folder/fused.ply``, else
    a preview from the dataset recorded in the report)."""
    from ...core.yamlio import atomic_write_text

    folder = Path(folder)
    tick = start(progress, "building report.html", 10, 0)
    cloud, why = load_cloud(report, folder)
    tick(1)
    text = render_html(report, cloud, why, tick)
    path = folder / "report.html"
    atomic_write_text(path, text)
    return path
