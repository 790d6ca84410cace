"""Calibrate from the thesis's pose-graph CSVs: ``Nodes.csv`` + ``Edges.csv`` -> extrinsics.

Library entry point of ``rgbd-calib posegraph NODES.csv EDGES.csv --out DIR``:
:func:`run_posegraph` solves, :func:`rgbd_calib.outputs.writer.write_posegraph_outputs` writes the
results.

Only the edges are measurements. From ``Nodes.csv`` only the reference is taken (the camera
whose node is the identity, else the first camera): its camera guesses are hand measurements
and its board nodes one camera's view, so the initialisation is rebuilt from the edges
(:func:`rgbd_calib.solve.posegraph.initialise_from_edges`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import PoseGraphConfig
from ..core.errors import CalibrationError
from ..core.yamlio import to_builtin
from ..model.posegraph_csv import camera_name, read_edges_csv, read_nodes_csv
from ..model.results import Extrinsics, PoseEdge, Verdict
from ..solve.posegraph import (
    EdgeResidual,
    PoseGraphResult,
    calibrate_pose_graph,
    median_edge_residual,
)

POSEGRAPH_REPORT = "posegraph_report.json"
POSEGRAPH_CONFIG = "posegraph_config.yaml"


@dataclass(frozen=True)
class PosegraphRun:
    """Result of :func:`run_posegraph`: the extrinsics, the per-edge residual table, the stale
    and outlier edge indices (0-based, in ``Edges.csv`` row order) and summary statistics."""

    extrinsics: Extrinsics
    residuals: tuple[EdgeResidual, ...]
    stale_edges: tuple[int, ...]
    outlier_edges: tuple[int, ...]
    stats: dict[str, Any]
    edges: tuple[PoseEdge, ...] = field(repr=False)
    result: PoseGraphResult = field(repr=False)
    config: PoseGraphConfig = field(default_factory=PoseGraphConfig)

    def to_dict(self) -> dict[str, Any]:
        """The ``posegraph_report.json`` content."""
        edge = {r.index: r for r in self.residuals}

        def rows(indices: tuple[int, ...]) -> list[dict[str, Any]]:
            return [
                {
                    "index": i,
                    "csv_row": i + 2,
                    "camera": edge[i].camera,
                    "view": edge[i].view,
                    "translation_mm": edge[i].translation_mm,
                    "rotation_deg": edge[i].rotation_deg,
                    "whitened_norm": edge[i].whitened_norm,
                }
                for i in indices
            ]

        cameras = {
            name: {
                **cam.to_dict(),
                "edges_used": sum(1 for r in self.residuals if r.used and r.camera == name),
            }
            for name, cam in self.extrinsics.cameras.items()
        }
        return to_builtin(
            {
                "reference": self.extrinsics.reference,
                "stats": self.stats,
                "cameras": cameras,
                "unconnected": self.extrinsics.unconnected,
                "stale_edges": rows(self.stale_edges),
                "outlier_edges": rows(self.outlier_edges),
                "edges": [r.to_dict() for r in self.residuals],
            }
        )


OUTLIER_SHARE_CHECK = 0.1  # more of the edges than this rejected as outliers: CHECK


def posegraph_verdict(extrinsics: Extrinsics, result: PoseGraphResult, n_edges: int) -> Verdict:
    """The pose graph's verdict, as calibrate's: POOR when a camera of the edges could not be
    calibrated; CHECK when a camera's edges disagree as a whole (a model error) or more than
    :data:`OUTLIER_SHARE_CHECK` of the edges were outliers; GOOD otherwise."""
    if extrinsics.unconnected:
        cams = sorted(extrinsics.unconnected)
        return Verdict("poor", f"not_calibrated [{', '.join(cams)}]: no edge chain links "
                       f"{'them' if len(cams) > 1 else 'it'} to the reference")
    if result.model_error:
        cams = sorted(result.model_error)
        return Verdict("check", f"camera_model_error [{', '.join(cams)}]: their edges disagree "
                       "with the rest of the graph as a whole; their sigmas are inflated")
    outliers = len(result.outlier_edges)
    if n_edges and outliers > OUTLIER_SHARE_CHECK * n_edges:
        return Verdict("check", f"outlier_edges: {outliers} of {n_edges} edges rejected as "
                       "outliers (posegraph_report.json lists them)")
    return Verdict("good", "no camera unlinked, no model error, few outlier edges")


def _reference(nodes: dict[str, np.ndarray], cameras: list[str]) -> str:
    """The camera whose ``Nodes.csv`` pose is the identity, else the first camera of
    ``Nodes.csv`` (or of ``Edges.csv`` when Nodes.csv lists none)."""
    node_cameras = [camera_name(n) for n in nodes if camera_name(n) in cameras]
    for node, T in nodes.items():
        if camera_name(node) in cameras and np.allclose(T, np.eye(4), atol=1e-9):
            return camera_name(node)
    return (node_cameras or cameras)[0]


def run_posegraph(
    nodes_csv: Path, edges_csv: Path, config: PoseGraphConfig | None = None
) -> PosegraphRun:
    """Solve the thesis pose graph in ``nodes_csv`` / ``edges_csv`` (see module doc)."""
    config = config or PoseGraphConfig()
    start = time.perf_counter()
    nodes = read_nodes_csv(Path(nodes_csv))
    edges = read_edges_csv(Path(edges_csv))
    cameras = list(dict.fromkeys(e.camera for e in edges))
    reference = _reference(nodes, cameras)
    result = calibrate_pose_graph(edges, reference, config)
    if len(result.cameras) < 2:
        raise CalibrationError(
            f"{edges_csv}: no camera shares a board view with the reference "
            f"{reference}; nothing to calibrate"
        )
    used_mm, used_deg = median_edge_residual(result.residuals, used_only=True)
    all_mm, all_deg = median_edge_residual(
        [r for r in result.residuals if not r.stale], used_only=False
    )
    stats = {
        **result.stats,
        "cameras": len(result.cameras),
        "median_edge_residual_used_mm": used_mm,
        "median_edge_residual_used_deg": used_deg,
        "median_edge_residual_nonstale_mm": all_mm,
        "median_edge_residual_nonstale_deg": all_deg,
        "default_sigma_rotation_deg": result.sigma_rotation_deg_default,
        "default_sigma_translation_mm": result.sigma_translation_mm_default,
        "seconds": time.perf_counter() - start,
    }
    extrinsics = result.to_extrinsics()
    return PosegraphRun(
        replace(extrinsics, verdict=posegraph_verdict(extrinsics, result, len(edges))),
        result.residuals,
        result.stale_edges,
        result.outlier_edges,
        stats,
        tuple(edges),
        result,
        config,
    )
