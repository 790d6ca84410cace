"""The thesis's pose-graph CSVs (docs/formats.md "Thesis pose-graph CSVs", thesis Figs 4.9/4.10).

- ``Nodes.csv``: ``Node ID tx ty tz qx qy qz qw``, each row ``T_ref_node`` (cameras and board
  views share one id space; rows with only an id are unused nodes and are skipped).
- ``Edges.csv``: ``Cam Node tx ty tz qx qy qz qw``, each row ``T_cam_board`` of view ``Node``.
- ``optimised_camera_poses.csv`` (the thesis's MATLAB result, Table 4.3):
  ``Camera ID tx ty tz qw qx qy qz`` (w first), each row ``T_ref_cam``.

Readers accept comma- or whitespace-separated rows, a UTF-8 BOM, CRLF line ends, and take the
pose columns by header name when the header names them (``tx`` ... ``qw``), else by position.
Numeric camera ids become camera names ``cam<ID>`` (``7`` -> ``cam7``). Metres throughout.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..core.errors import ConfigError
from ..core.geometry import make_transform, matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from ..core.yamlio import atomic_write_text
from .results import PoseEdge

POSE_XYZW = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
POSE_WXYZ = ("tx", "ty", "tz", "qw", "qx", "qy", "qz")
NODES_HEADER = "Node ID,tx,ty,tz,qx,qy,qz,qw"
EDGES_HEADER = "Cam,Node ID,tx,ty,tz,qx,qy,qz,qw"
CAMERA_POSES_HEADER = "Camera ID,tx,ty,tz,qw,qx,qy,qz"
_INTEGER_FLOAT = re.compile(r"^[+-]?\d+\.0*$")


def camera_name(node_id: str) -> str:
    """Thesis camera node id -> camera name: ``"7"`` -> ``"cam7"``; other names unchanged."""
    return f"cam{node_id}" if node_id.isdigit() else node_id


def camera_node_id(name: str) -> str:
    """Camera name -> thesis node id: ``"cam7"`` -> ``"7"``; other names unchanged."""
    return name[3:] if name.startswith("cam") and name[3:].isdigit() else name


# ---------------------------------------------------------------------------------------------
# Reading


def _split(line: str) -> list[str]:
    if "," in line:
        return [f.strip() for f in line.split(",")]
    return line.split()


def _node_token(token: str) -> str:
    return str(int(float(token))) if _INTEGER_FLOAT.match(token) else token


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _read_rows(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """Non-blank rows ``(line number, fields)`` of a CSV, header included."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: {what} not found; check the path")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: {what} is not UTF-8 text; save it as UTF-8 CSV") from exc
    return [(n, _split(line)) for n, line in enumerate(text.splitlines(), start=1) if line.strip()]


def _pose_columns(header: list[str] | None, n_ids: int, default: tuple[str, ...]) -> list[int]:
    """Column index of each of tx ty tz qx qy qz qw (in that order). The pose is the last 7
    columns; their order comes from the header's last 7 names when those are tx ... qw (a
    whitespace-separated header may split "Node ID" in two, so names are matched from the
    end), else ``default``."""
    names = [h.strip().lower().replace("_", "") for h in (header or [])[-7:]]
    order = tuple(names) if sorted(names) == sorted(POSE_XYZW) else default
    return [n_ids + order.index(key) for key in POSE_XYZW]


def _pose(path: Path, line: int, fields: list[str], columns: list[int]) -> np.ndarray:
    values = []
    for key, col in zip(POSE_XYZW, columns, strict=True):
        token = fields[col]
        try:
            value = float(token)
        except ValueError:
            raise ConfigError(
                f"{path}: row {line}: column {key} is not a number ({token!r}); fix the value"
            ) from None
        if not math.isfinite(value):
            raise ConfigError(
                f"{path}: row {line}: column {key} is {token}; every pose value must be finite"
            )
        values.append(value)
    q = np.asarray(values[3:])
    if np.linalg.norm(q) < 1e-9:
        raise ConfigError(
            f"{path}: row {line}: quaternion qx qy qz qw is all zeros; write a unit "
            "quaternion (0 0 0 1 for no rotation)"
        )
    return make_transform(quaternion_xyzw_to_matrix(q), values[:3])


def _table(
    path: Path, what: str, id_names: tuple[str, ...], default: tuple[str, ...], allow_empty: bool
) -> list[tuple[int, list[str], np.ndarray | None]]:
    """Rows ``(line, ids, T)`` with ``T`` None for an id-only row (when ``allow_empty``)."""
    path = Path(path)
    rows = _read_rows(path, what)
    header = None
    if rows and not _is_number(rows[0][1][0]):
        header = rows.pop(0)[1]
    columns = _pose_columns(header, len(id_names), default)
    width = len(id_names) + 7
    expected = " ".join((*id_names, *default))
    out = []
    for line, fields in rows:
        ids = [_node_token(f) for f in fields[: len(id_names)]]
        rest = fields[len(id_names) :]
        if allow_empty and len(fields) <= width and not any(rest) and all(ids):
            out.append((line, ids, None))
            continue
        if len(fields) != width:
            raise ConfigError(
                f"{path}: row {line}: expected {width} values ({expected}), got "
                f"{len(fields)}; fix or delete the row"
            )
        if not all(ids):
            raise ConfigError(
                f"{path}: row {line}: empty {' / '.join(id_names)}; every row needs its id(s)"
            )
        out.append((line, ids, _pose(path, line, fields, columns)))
    if not any(T is not None for _, _, T in out):
        raise ConfigError(f"{path}: {what} has no pose rows; expected rows of {expected}")
    return out


def read_nodes_csv(path: Path) -> dict[str, np.ndarray]:
    """``Nodes.csv`` -> ``{node id: T_ref_node}`` (4x4, metres) in file order; unused
    (id-only) rows are skipped. Ids are kept as written (``"7"``, ``"23"``)."""
    nodes: dict[str, np.ndarray] = {}
    for line, (node,), T in _table(path, "Nodes.csv", ("node",), POSE_XYZW, allow_empty=True):
        if T is None:
            continue
        if node in nodes:
            raise ConfigError(
                f"{path}: row {line}: node {node} appears twice; keep one row per node"
            )
        nodes[node] = T
    return nodes


def read_edges_csv(path: Path) -> list[PoseEdge]:
    """``Edges.csv`` -> edges in file order (order matters for stale-edge detection): camera
    ``cam<Cam>``, view ``<Node>``, ``T_cam_board`` (4x4, metres), no covariance."""
    return [
        PoseEdge(camera_name(cam), node, T)
        for _, (cam, node), T in _table(
            path, "Edges.csv", ("cam", "node"), POSE_XYZW, allow_empty=False
        )
    ]


def read_optimised_camera_poses(path: Path) -> dict[str, np.ndarray]:
    """The thesis result ``optimised_camera_poses.csv`` (``tx ty tz qw qx qy qz``, w first)
    -> ``{camera name: T_ref_cam}`` (4x4, metres)."""
    out: dict[str, np.ndarray] = {}
    for line, (cam,), T in _table(
        path, "camera poses CSV", ("camera",), POSE_WXYZ, allow_empty=False
    ):
        name = camera_name(cam)
        if name in out:
            raise ConfigError(f"{path}: row {line}: camera {cam} appears twice; keep one row")
        out[name] = T
    return out


# ---------------------------------------------------------------------------------------------
# Writing


def _pose_fields(T: np.ndarray, order: tuple[str, ...] = POSE_XYZW) -> list[str]:
    T = np.asarray(T, dtype=float)
    q = matrix_to_quaternion_xyzw(T[:3, :3])
    values = dict(zip(POSE_XYZW, [*T[:3, 3], *q], strict=True))
    return [repr(float(values[key])) for key in order]


def node_ids(cameras: list[str], views: list[str]) -> tuple[dict[str, str], dict[str, str]]:
    """Camera and view node ids in the one id space of ``Nodes.csv``/``Edges.csv``.

    A camera's id is its thesis number (``cam7`` -> ``7``) unless a view has that id; then it
    keeps its name (``cam7``: read back, the name is the same camera). A view whose id is still
    taken (a camera literally named like it) becomes ``view<id>``."""
    view_set = set(views)
    cams = {c: (n if (n := camera_node_id(c)) not in view_set else c) for c in cameras}
    taken = set(cams.values())
    out_views = {}
    for v in views:
        node = v
        while node in taken:
            node = f"view{node}"
        out_views[v] = node
        taken.add(node)
    return cams, out_views


def nodes_csv_text(
    T_ref_cam: dict[str, np.ndarray], T_ref_board: dict[str, np.ndarray] | None = None
) -> str:
    """Thesis-style ``Nodes.csv`` text: cameras first (ids ``cam7`` -> ``7``), then views
    (ids by :func:`node_ids`)."""
    rows = [NODES_HEADER]
    boards = T_ref_board or {}
    cam_ids, view_ids = node_ids(list(T_ref_cam), list(boards))
    for cam, T in T_ref_cam.items():
        rows.append(",".join([cam_ids[cam], *_pose_fields(T)]))
    for view, T in boards.items():
        rows.append(",".join([view_ids[view], *_pose_fields(T)]))
    return "\n".join(rows) + "\n"


def edges_csv_text(edges: list[PoseEdge], views: list[str] | None = None,
                   cameras: list[str] | None = None) -> str:
    """Thesis-style ``Edges.csv`` text, one ``T_cam_board`` row per edge; ``views`` and
    ``cameras`` (default: the edges') are the nodes of the ``Nodes.csv`` it goes with, so both
    files number them alike (:func:`node_ids`)."""
    views = list(dict.fromkeys([*(views or []), *(e.view for e in edges)]))
    cameras = list(dict.fromkeys([*(cameras or []), *(e.camera for e in edges)]))
    cam_ids, view_ids = node_ids(cameras, views)
    rows = [EDGES_HEADER]
    rows += [
        ",".join([cam_ids[e.camera], view_ids[e.view], *_pose_fields(e.T_cam_board)])
        for e in edges
    ]
    return "\n".join(rows) + "\n"


def write_nodes_csv(
    path: Path, T_ref_cam: dict[str, np.ndarray], T_ref_board: dict[str, np.ndarray] | None = None
) -> None:
    """Write ``Nodes.csv`` atomically from ``T_ref_cam`` / ``T_ref_board`` (4x4, metres)."""
    atomic_write_text(Path(path), nodes_csv_text(T_ref_cam, T_ref_board))


def write_edges_csv(path: Path, edges: list[PoseEdge]) -> None:
    """Write ``Edges.csv`` atomically."""
    atomic_write_text(Path(path), edges_csv_text(edges))


def write_optimised_camera_poses(path: Path, T_ref_cam: dict[str, np.ndarray]) -> None:
    """Write ``optimised_camera_poses.csv`` (thesis Table 4.3 layout, quaternion w first)."""
    rows = [CAMERA_POSES_HEADER]
    rows += [
        ",".join([camera_node_id(c), *_pose_fields(T, POSE_WXYZ)]) for c, T in T_ref_cam.items()
    ]
    atomic_write_text(Path(path), "\n".join(rows) + "\n")
