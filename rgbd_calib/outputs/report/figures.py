"""The report's figures: matplotlib PNGs, base64-encoded for embedding (no metadata, so a
rebuild gives identical bytes). The only module of the package that imports matplotlib,
and only inside functions.
"""

from __future__ import annotations

import base64
import io
import math
from typing import Any

import numpy as np

from ...core.progress import Tick
from .cloud import Cloud
from .layout import board_outline, frustum, rig_size
from .numbers import fmt, median_or_none
from .schema import COVERAGE_GRID, view_in_estimate

REF_COLOR = (0.84, 0.15, 0.16)  # the reference camera is red, as in the thesis's Fig. 4.11


def palette(report: dict[str, Any]) -> list[tuple[float, float, float]]:
    """One colour per camera (rig order), the same in every figure and in the 3D view: the
    reference red, the others from a qualitative map without red."""
    import matplotlib

    others = len(report["cameras"]) - 1
    if others <= 18:
        name, reds = ("tab10", {3}) if others <= 9 else ("tab20", {6, 7})
        cmap = matplotlib.colormaps[name]
        pool = [tuple(cmap(i)[:3]) for i in range(cmap.N) if i not in reds]
    else:
        hsv = matplotlib.colormaps["hsv"]
        pool = [tuple(hsv(0.08 + 0.84 * i / others)[:3]) for i in range(others)]
    it = iter(pool)
    return [REF_COLOR if c == report["reference"] else next(it) for c in report["cameras"]]


def _png(fig) -> str:
    """A matplotlib figure as a base64 PNG (no metadata: identical bytes on a rebuild)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=96, metadata={"Software": None})
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _figure(w: float, h: float, **kw):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 9, "axes.titlesize": 10, "svg.hashsalt": "rgbd-calib"})
    return plt.subplots(figsize=(w, h), layout="constrained", **kw)


def label_row(anchor: tuple[float, float], placed: list[tuple[float, float]],
              size: float) -> int:
    """How many lines up a camera label goes: one per earlier label anchored within 8% (across)
    and 4% (up) of the rig's size, so cameras that project close together (the side view of
    facing cameras) get stacked labels instead of labels printed over each other."""
    u, v = anchor
    return sum(abs(u - pu) < 0.08 * size and abs(v - pv) < 0.04 * size for pu, pv in placed)


def _draw_rig(
    ax,
    report: dict[str, Any],
    frame: np.ndarray,
    axes: tuple[int, int],
    colors: list,
    boards: bool = True,
) -> None:
    """Cameras as frusta (reference in red, bold) and board poses projected on ``axes``."""
    from matplotlib.collections import LineCollection, PolyCollection

    size = rig_size(report)
    a, b = axes
    if boards and report["board_views"]:
        Ts = [np.asarray(bv["T_ref_board"], float) for bv in report["board_views"]]
        outlines = np.array([board_outline(report, T) @ frame.T for T in Ts])[:, :, [a, b]]
        ax.add_collection(
            PolyCollection(outlines, facecolor=(0.55, 0.55, 0.55, 0.12), edgecolor="0.45", lw=0.5)
        )
        step = max(1, len(Ts) // 40)  # every k-th board pose as a 3D axis (thesis Fig. 4.11)
        for axis, col in zip(range(3), ("tab:red", "tab:green", "tab:blue")):
            segs = [
                np.array([T[:3, 3], T[:3, 3] + T[:3, axis] * 0.08 * size / 1.5]) @ frame.T
                for T in Ts[::step]
            ]
            ax.add_collection(LineCollection([s[:, [a, b]] for s in segs], colors=col, lw=0.8))
    placed: list[tuple[float, float]] = []  # label anchors so far (data units)
    for i, (name, cam) in enumerate(report["cameras"].items()):
        if cam["T_ref_cam"] is None:
            continue
        f = frustum(cam, 0.12 * size) @ frame.T
        ref = name == report["reference"]
        col = colors[i]
        for j in range(1, 5):
            ax.plot([f[0, a], f[j, a]], [f[0, b], f[j, b]], color=col, lw=1.6 if ref else 1.0)
        ring = f[[1, 2, 3, 4, 1]]
        ax.plot(ring[:, a], ring[:, b], color=col, lw=1.6 if ref else 1.0)
        near = label_row((f[0, a], f[0, b]), placed, size)
        placed.append((f[0, a], f[0, b]))
        ax.annotate(
            name + (" (ref)" if ref else ""),
            (f[0, a], f[0, b]),
            fontsize=8,
            xytext=(3, 3 + 10 * near),
            textcoords="offset points",
            color=col,
            fontweight="bold" if ref else "normal",
        )
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3, alpha=0.5)


def fig_rig(report: dict[str, Any], frame: np.ndarray) -> str:
    fig, (top, side) = _figure(11, 4.6, ncols=2)
    colors = palette(report)
    _draw_rig(top, report, frame, (0, 1), colors)
    _draw_rig(side, report, frame, (0, 2), colors)
    top.set(title="top view (looking down)", xlabel="e1 (m)", ylabel="e2 (m)")
    side.set(title="side view", xlabel="e1 (m)", ylabel="up (m)")
    return _png(fig)


def fig_cloud(report: dict[str, Any], cloud: Cloud, frame: np.ndarray) -> str:
    fig, (top, side) = _figure(11, 4.6, ncols=2)
    colors = np.array(palette(report))
    p = cloud.points @ frame.T
    order = np.argsort(p[:, 2])  # top view: higher points drawn last
    for ax, (a, b), idx in ((top, (0, 1), order), (side, (0, 2), np.argsort(-p[:, 1]))):
        ax.scatter(
            p[idx, a], p[idx, b], s=0.6, c=colors[cloud.camera[idx]], linewidths=0, rasterized=True
        )
        _draw_rig(ax, report, frame, (a, b), list(map(tuple, colors)), boards=False)
    top.set(title="fused cloud, top view (colour = camera)", xlabel="e1 (m)", ylabel="e2 (m)")
    side.set(title="fused cloud, side view", xlabel="e1 (m)", ylabel="up (m)")
    return _png(fig)


def fig_histograms(report: dict[str, Any]) -> str:
    names = list(report["cameras"])
    edges = np.asarray(report["reprojection_histogram_edges_px"])
    cols = min(4, len(names))
    rows = math.ceil(len(names) / cols)
    fig, axes = _figure(2.8 * cols, 2.0 * rows, nrows=rows, ncols=cols, squeeze=False, sharex=True)
    colors = palette(report)
    rig_p50 = median_or_none(
        [(c["reprojection_px"] or {}).get("p50") for c in report["cameras"].values()]
    )
    flagged = {c for w in report["warnings"] if w["severity"] != "info" for c in w["cameras"]}
    for k, ax in enumerate(axes.ravel()):
        if k >= len(names):
            ax.axis("off")
            continue
        name = names[k]
        cam = report["cameras"][name]
        h = cam["reprojection_histogram"]
        ax.bar(edges[:-1], h["used"], width=np.diff(edges), align="edge", color=colors[k])
        ax.bar(
            edges[:-1],
            h["excluded"],
            width=np.diff(edges),
            align="edge",
            bottom=h["used"],
            color="0.6",
            label="excluded",
        )
        st = cam["reprojection_px"]
        if st:
            ax.axvline(min(st["p50"], edges[-1]), color="k", lw=1)
            ax.axvline(min(st["p90"], edges[-1]), color="k", lw=1, ls=":")
        if rig_p50:
            ax.axvline(rig_p50, color="0.35", lw=0.9, ls="--")
        over = h["used"][-1] + h["excluded"][-1]
        if over:
            ax.annotate(
                f"last bin: {over} >= {edges[-2]:.2g} px",
                (1, 1),
                xycoords="axes fraction",
                ha="right",
                va="top",
                fontsize=7,
            )
        title = f"{name}: p50 {fmt(st['p50'] if st else None)} px"
        ax.set_title(title, color="red" if name in flagged else "black", fontsize=9)
        # a little air between the bars and the frame
        ax.set_xlim(-0.02 * edges[-1], 1.02 * edges[-1])
        ax.set_ylim(0, 1.15 * max(1, max(u + e for u, e in zip(h["used"], h["excluded"]))))
    for ax in axes[-1]:
        ax.set_xlabel("marker reprojection RMS (px)")
    for ax in axes[:, 0]:
        ax.set_ylabel("markers")
    return _png(fig)


def fig_edges(report: dict[str, Any]) -> str:
    """Residual of every pose-graph edge (camera, board view), like the thesis's Fig. 5.2."""
    names = list(report["cameras"])
    colors = palette(report)
    views = report["views"]
    fig, axes = _figure(11, 6.2, nrows=3, sharex=True)
    x = np.arange(len(views))
    panels = (
        ("edge_translation_mm", "translation residual (mm)"),
        ("edge_rotation_deg", "rotation residual (deg)"),
        ("final_reprojection_rms_px", "final reprojection RMS (px)"),
    )
    for ax, (key, label) in zip(axes, panels):
        for k, name in enumerate(names):
            sel = [
                i
                for i, v in enumerate(views)
                if v["camera"] == name and v[key] is not None and v["edge_status"] == "used"
            ]
            ax.scatter(
                x[sel],
                [max(views[i][key], 1e-4) for i in sel],
                s=9,
                color=colors[k],
                label=name if key == panels[0][0] else None,
            )
        bad = [
            i
            for i, v in enumerate(views)
            if v["edge_status"] in ("outlier", "stale") and v[key] is not None
        ]
        if bad:
            ax.scatter(
                x[bad],
                [max(views[i][key], 1e-4) for i in bad],
                s=30,
                marker="x",
                color="red",
                label="outlier / stale" if key == panels[0][0] else None,
            )
        if any(len(c.get_offsets()) for c in ax.collections):  # an empty axis cannot be log
            ax.set_yscale("log")
        else:
            ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center")
        ax.set_ylabel(label)
        ax.grid(True, which="major", lw=0.3, alpha=0.6)
    axes[0].legend(
        ncol=min(len(names) + 1, 9),
        fontsize=7,
        loc="lower left",
        bbox_to_anchor=(0, 1.02),
        frameon=False,
    )
    axes[-1].set_xlabel("edge id (board views in frame order, cameras within a frame)")
    return _png(fig)


def fig_covisibility(report: dict[str, Any]) -> str:
    cov = report["covisibility"]
    names, m = cov["cameras"], np.asarray(cov["views"])
    n = len(names)
    fig, ax = _figure(1.2 + 0.55 * n, 1.0 + 0.5 * n)
    off = m.astype(float).copy()
    np.fill_diagonal(off, np.nan)
    im = ax.imshow(
        np.where(np.eye(n, dtype=bool), np.nan, m),
        cmap="viridis",
        vmin=0,
        vmax=max(np.nanmax(off) if n > 1 else 1, 1),
    )
    for i in range(n):
        for j in range(n):
            ax.text(
                j,
                i,
                str(m[i, j]),
                ha="center",
                va="center",
                fontsize=8,
                color="black"
                if i == j
                else ("white" if m[i, j] < 0.6 * np.nanmax(off if n > 1 else m) else "black"),
                fontweight="bold" if i == j else "normal",
            )
    ax.set_xticks(range(n), names, rotation=45, ha="right")
    ax.set_yticks(range(n), names)
    ax.set_title("board views shared (diagonal: views used)")
    fig.colorbar(im, ax=ax, shrink=0.8, label="shared views")
    return _png(fig)


def fig_coverage(report: dict[str, Any]) -> str:
    """Where in each image the board was: how many used views' marker bounding boxes cover
    each cell (views left out are not counted)."""
    names = list(report["cameras"])
    cols = min(4, len(names))
    rows = math.ceil(len(names) / cols)
    fig, axes = _figure(2.8 * cols, 1.9 * rows, nrows=rows, ncols=cols, squeeze=False)
    gx, gy = COVERAGE_GRID
    for k, ax in enumerate(axes.ravel()):
        if k >= len(names):
            ax.axis("off")
            continue
        name = names[k]
        cam = report["cameras"][name]
        w, h = cam["intrinsics"]["width"], cam["intrinsics"]["height"]
        uu, vv = np.meshgrid((np.arange(gx) + 0.5) * w / gx, (np.arange(gy) + 0.5) * h / gy)
        count = np.zeros(uu.shape)
        left_out = 0
        for v in report["views"]:
            if v["camera"] != name:
                continue
            if not view_in_estimate(v):
                left_out += 1
                continue
            u0, v0, u1, v1 = v["image_bbox_px"]
            count += (u0 <= uu) & (uu <= u1) & (v0 <= vv) & (vv <= v1)
        ax.imshow(
            np.where(count > 0, count, np.nan),
            cmap="viridis",
            vmin=0,
            vmax=max(count.max(), 1),
            extent=(0, w, h, 0),
            interpolation="nearest",
        )
        ax.set_facecolor("#f3f3f3")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_xticks([])
        ax.set_yticks([])
        cov = cam["coverage"]
        extra = f", {left_out} left out" if left_out else ""
        ax.set_title(f"{name}: {cov['image_fraction']:.0%} covered{extra}", fontsize=9)
    return _png(fig)


def fig_distance(report: dict[str, Any]) -> str:
    """Board distance and tilt of every view per camera (front o, back s, left out x)."""
    names = list(report["cameras"])
    colors = palette(report)
    fig, (ad, at) = _figure(11, 3.0, ncols=2)
    for k, name in enumerate(names):
        mine = [v for v in report["views"] if v["camera"] == name]
        x = k + 0.05 * ((np.arange(len(mine)) % 7) - 3)  # spread one camera's dots a little
        for marker, color, pick in (
            ("o", colors[k], lambda v: v["edge_status"] == "used" and v["face"] != "back"),
            ("s", colors[k], lambda v: v["edge_status"] == "used" and v["face"] == "back"),
            ("x", "red", lambda v: v["edge_status"] != "used"),
        ):
            sel = [i for i, v in enumerate(mine) if pick(v)]
            if not sel:
                continue
            for ax, key in ((ad, "distance_m"), (at, "tilt_deg")):
                ax.scatter(x[sel], [mine[i][key] for i in sel], s=16, marker=marker, color=color)
    for ax, label in ((ad, "board distance (m)"), (at, "board tilt to the ray (deg)")):
        ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
        ax.set_ylabel(label)
        ax.grid(True, lw=0.3, alpha=0.6)
    ad.set_title("distance per view (o front face, s back face, x left out)")
    at.set_title("tilt per view")
    return _png(fig)


def fig_markers(report: dict[str, Any]) -> str:
    ms = report["markers"]
    fig, ax = _figure(11, 2.4)
    if ms:
        x = np.arange(len(ms))
        ax.bar(
            x,
            [m["rms_px"] for m in ms],
            color=["tab:blue" if m["face"] == "front" else "tab:orange" for m in ms],
        )
        ax.set_xticks(x, [str(m["id"]) for m in ms], fontsize=7)
        med = median_or_none([m["rms_px"] for m in ms])
        ax.axhline(med, color="k", lw=0.8, ls="--")
    ax.set(
        xlabel="marker id (blue front face, orange back face)",
        ylabel="reprojection RMS (px)",
        title="final reprojection error per marker",
    )
    return _png(fig)


def fig_error_maps(report: dict[str, Any]) -> str:
    pairs = [p for p in report["pairs"] if p["error_map"]]
    cols = min(3, len(pairs))
    rows = math.ceil(len(pairs) / cols)
    fig, axes = _figure(3.6 * cols, 2.4 * rows, nrows=rows, ncols=cols, squeeze=False)
    vals = np.array([v for p in pairs for v in p["error_map"]["values_mm"] if v is not None])
    lim = float(np.percentile(np.abs(vals), 95)) if vals.size else 1.0
    im = None
    for k, ax in enumerate(axes.ravel()):
        if k >= len(pairs):
            ax.axis("off")
            continue
        em = pairs[k]["error_map"]
        grid = np.array([np.nan if v is None else v for v in em["values_mm"]], float)
        im = ax.imshow(
            grid.reshape(em["rows"], em["cols"]),
            cmap="coolwarm",
            vmin=-lim,
            vmax=lim,
            extent=(0, em["width"], em["height"], 0),
        )
        ax.set_title(f"{pairs[k]['cam_a']} vs {pairs[k]['cam_b']}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.8, label="point-to-plane distance (mm)")
    return _png(fig)


def render_figures(
    report: dict[str, Any], cloud: Cloud | None, frame: np.ndarray, tick: Tick
) -> dict[str, str | None]:
    """Every figure of the page by key (None: not drawn), ``tick(1)`` after each."""
    figs: dict[str, str | None] = {}
    board_only = ("hist", "edges", "covis", "coverage", "distance", "markers")
    depth_only = report.get("refine") is not None  # no board result: no board figure
    for key, fn in (
        ("rig", lambda: fig_rig(report, frame)),
        ("hist", lambda: fig_histograms(report)),
        ("edges", lambda: fig_edges(report)),
        ("covis", lambda: fig_covisibility(report)),
        ("coverage", lambda: fig_coverage(report)),
        ("distance", lambda: fig_distance(report)),
        ("markers", lambda: fig_markers(report)),
        ("cloud", lambda: fig_cloud(report, cloud, frame) if cloud else None),
        (
            "errmap",
            lambda: (
                fig_error_maps(report) if any(p["error_map"] for p in report["pairs"]) else None
            ),
        ),
    ):
        figs[key] = None if depth_only and key in board_only else fn()
        tick(1)
    return figs
