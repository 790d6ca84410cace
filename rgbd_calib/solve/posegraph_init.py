"""Stale edges and the pose graph's initialisation from the edges alone (numpy only).

:func:`initialise_from_edges` chains the cameras from the reference along a maximum spanning
tree of their co-visibility graph with robust relative poses (:func:`robust_mean_pose`), so the
solve (:mod:`rgbd_calib.solve.posegraph`) needs no hand-measured guesses; :func:`flag_stale_edges`
finds the rows a recorder re-reported instead of measuring.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from ..core.errors import CalibrationError
from ..core.geometry import invert_transform, orthonormalize
from ..model.results import PoseEdge

REASON_NO_SHARED_VIEW = "shares no board view with any connected camera"


def flag_stale_edges(edges: list[PoseEdge]) -> set[int]:
    """Indices of edges whose ``T_cam_board`` equals the same camera's previous edge exactly.

    The thesis recorder re-used the last detected pose when a camera missed the board, so such
    a row is not a measurement of its view. Order matters: "previous" is list (file) order."""
    stale: set[int] = set()
    previous: dict[str, np.ndarray] = {}
    for i, edge in enumerate(edges):
        T = np.asarray(edge.T_cam_board, dtype=float)
        last = previous.get(edge.camera)
        if last is not None and np.array_equal(T, last):
            stale.add(i)
        previous[edge.camera] = T
    return stale


def _pose_distances(T: np.ndarray, length_m: float) -> np.ndarray:
    """Pairwise distance of poses ``(N,4,4)``: ``|t_i - t_j| + length_m * angle(R_i^T R_j)``,
    i.e. how far a point ``length_m`` in front of the frame moves (metres)."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    cos = (np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return np.linalg.norm(t[:, None] - t[None], axis=-1) + length_m * angle


def robust_mean_pose(T: np.ndarray, length_m: float = 1.0) -> np.ndarray:
    """Robust mean of pose estimates ``(N,4,4)`` of the same ``T_a_b``.

    The medoid (the estimate with the smallest median :func:`_pose_distances` to the others)
    is robust to < 50% gross outliers; the result is the chordal mean (SVD-projected sum of
    rotations, mean translation) of the estimates within 3x the median distance to the medoid,
    which recovers the averaging efficiency of a mean on the inliers."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    if len(T) <= 2:
        return T[0].copy()
    d = _pose_distances(T, length_m)
    medoid = int(np.argmin(np.median(d, axis=1)))
    to_medoid = d[medoid]
    keep = to_medoid <= 3.0 * np.median(to_medoid) + 1e-12
    out = np.eye(4)
    out[:3, :3] = orthonormalize(T[keep, :3, :3].sum(axis=0))
    out[:3, 3] = T[keep, :3, 3].mean(axis=0)
    return out


def _observations(edges: list[PoseEdge], skip: set[int]) -> dict[str, dict[str, np.ndarray]]:
    """view -> camera -> T_cam_board (first edge of a camera/view pair wins)."""
    obs: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
    for i, e in enumerate(edges):
        if i not in skip:
            obs[e.view].setdefault(e.camera, np.asarray(e.T_cam_board, dtype=float))
    return obs


def working_distance_m(edges: list[PoseEdge]) -> float:
    """Median camera-to-board distance of ``edges`` (m; at least 0.1, 1 without edges): the
    lever arm :func:`robust_mean_pose` weighs rotations by."""
    if not edges:
        return 1.0
    return max(float(np.median([np.linalg.norm(e.T_cam_board[:3, 3]) for e in edges])), 0.1)


def initialise_from_edges(
    edges: list[PoseEdge], reference: str
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, str]]:
    """Initial ``T_ref_cam`` and ``T_ref_board`` (4x4, metres) from the edges alone.

    1. Co-visibility graph of the cameras: weight of (a, b) = number of board views both see
       (stale edges ignored).
    2. Maximum spanning tree grown from ``reference`` (Prim; ties broken by camera order).
    3. Each tree edge gets ``T_camA_camB = robust_mean_pose({T_camA_board_v @ T_board_v_camB})``
       over the shared views (medoid + trimmed chordal mean, see :func:`robust_mean_pose`),
       and the poses are chained from the reference.
    4. A board view is initialised with the robust mean of ``T_ref_cam @ T_cam_board`` over its
       connected cameras when three or more see it, else from the one closest to the
       reference in the tree.

    Returns ``(init_T_ref_cam, init_T_ref_board, unconnected)`` where ``unconnected`` maps a
    camera that cannot be chained to the reference to the reason."""
    stale = flag_stale_edges(edges)
    obs = _observations(edges, stale)
    cameras = list(dict.fromkeys(e.camera for e in edges))
    if reference not in cameras:
        raise CalibrationError(
            f"reference camera {reference!r} has no board observation; pick a camera that saw "
            "the board"
        )
    order = {c: i for i, c in enumerate(cameras)}
    shared: dict[tuple[str, str], list[str]] = defaultdict(list)
    for view, seen in obs.items():
        names = sorted(seen, key=order.__getitem__)
        for ia, a in enumerate(names):
            for b in names[ia + 1 :]:
                shared[(a, b)].append(view)
                shared[(b, a)].append(view)
    length_m = working_distance_m([e for i, e in enumerate(edges) if i not in stale])

    T_ref_cam = {reference: np.eye(4)}
    depth = {reference: 0}
    while True:  # Prim: the heaviest edge from the tree to a camera outside it
        frontier = [
            (len(shared[(a, b)]), -order[a], -order[b], a, b)
            for a in T_ref_cam
            for b in cameras
            if b not in T_ref_cam and (a, b) in shared
        ]
        if not frontier:
            break
        *_, a, b = max(frontier)
        T_a_b = robust_mean_pose(
            np.stack([obs[v][a] @ invert_transform(obs[v][b]) for v in shared[(a, b)]]), length_m
        )
        T_ref_cam[b] = T_ref_cam[a] @ T_a_b
        depth[b] = depth[a] + 1
    unconnected = {c: REASON_NO_SHARED_VIEW for c in cameras if c not in T_ref_cam}

    T_ref_board: dict[str, np.ndarray] = {}
    for view, seen in obs.items():
        connected = sorted((c for c in seen if c in T_ref_cam), key=lambda c: (depth[c], order[c]))
        if not connected:
            continue
        candidates = np.stack([T_ref_cam[c] @ seen[c] for c in connected])
        T_ref_board[view] = (
            robust_mean_pose(candidates, length_m) if len(connected) >= 3 else candidates[0]
        )
    return T_ref_cam, T_ref_board, unconnected

