"""The fused point cloud's file: binary little-endian PLY with a per-point camera index
(numpy only; written by calibrate/refine, read by the report and by users' tools).

Vertex properties ``x y z`` (float32, metres, reference frame), ``red green blue`` (uchar) and
``camera`` (uchar, or ushort beyond 256 cameras) indexing the header comments
``comment camera <index> <name>``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import DatasetError

# PLY scalar type names (both spellings) -> numpy little-endian dtypes
_PLY_TYPES = {
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
    "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
    "ushort": "<u2", "uint16": "<u2", "short": "<i2", "int16": "<i2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
}  # fmt: skip


def _fused_dtype(n_cameras: int) -> np.dtype:
    cam = "u1" if n_cameras <= 256 else "<u2"
    return np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                     ("blue", "u1"), ("camera", cam)])  # fmt: skip


def write_fused_ply(
    path: Path,
    points: np.ndarray,
    colors: np.ndarray,
    camera_index: np.ndarray,
    camera_names: list[str],
) -> None:
    """Write ``points`` (N,3) m, ``colors`` (N,3) in [0,1] and ``camera_index`` (N,) into
    ``camera_names``, atomically (temporary file + rename)."""
    path = Path(path)
    n = int(np.asarray(points).shape[0])
    if len(colors) != n or len(camera_index) != n:
        raise ValueError("points, colors and camera_index need the same length")
    if len(camera_names) > 65536:
        raise ValueError("at most 65536 cameras fit the camera property")
    idx = np.asarray(camera_index)
    if n and (idx.min() < 0 or idx.max() >= len(camera_names)):
        raise ValueError("camera_index outside camera_names")
    dtype = _fused_dtype(len(camera_names))
    data = np.empty(n, dtype=dtype)
    p = np.asarray(points, dtype=float)
    data["x"], data["y"], data["z"] = p[:, 0], p[:, 1], p[:, 2]
    rgb = np.clip(np.rint(np.asarray(colors, dtype=float) * 255.0), 0, 255).astype(np.uint8)
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    data["camera"] = idx
    cam_type = "uchar" if dtype["camera"].itemsize == 1 else "ushort"
    header = ["ply", "format binary_little_endian 1.0", "comment rgbd-calib fused cloud"]
    header += [f"comment camera {k} {name}" for k, name in enumerate(camera_names)]
    header += [f"element vertex {n}", "property float x", "property float y",
               "property float z", "property uchar red", "property uchar green",
               "property uchar blue", f"property {cam_type} camera", "end_header"]  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(data.tobytes())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, list[str]]:
    """Points (N,3) float, RGB (N,3) uint8 or None, camera index (N,) int or None, and the
    camera names of a binary little-endian PLY with scalar vertex properties (``fused.ply``, or
    any such cloud with ``x y z``). Raises :class:`DatasetError` naming the file otherwise."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: not a PLY file; delete it or re-run calibrate")
    body = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", "replace").splitlines()
    if not any(h.strip() == "format binary_little_endian 1.0" for h in header):
        raise DatasetError(f"{path}: only binary little-endian PLY is supported")
    fields, n, names, in_vertex = [], 0, {}, False
    for line in header:
        parts = line.split()
        if parts[:2] == ["comment", "camera"] and len(parts) >= 4:
            names[int(parts[2])] = " ".join(parts[3:])
        elif parts[:1] == ["element"]:
            in_vertex = parts[1] == "vertex"
            n = int(parts[2]) if in_vertex else n
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise DatasetError(f"{path}: unsupported PLY property {line.strip()!r}")
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    data = np.frombuffer(raw, dtype=np.dtype(fields), count=n, offset=body)
    points = np.column_stack([data["x"], data["y"], data["z"]]).astype(float)
    keys = {f for f, _ in fields}
    rgb = (
        np.column_stack([data["red"], data["green"], data["blue"]]).astype(np.uint8)
        if {"red", "green", "blue"} <= keys
        else None
    )
    cam = data["camera"].astype(np.int32) if "camera" in keys else None
    return points, rgb, cam, [names[k] for k in sorted(names)]
