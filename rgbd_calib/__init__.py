"""rgbd-calib: extrinsic calibration of multi-camera RGB-D rigs with a double-sided ArUco board.

The library API (names load on first use, so ``import rgbd_calib`` stays light)::

    from rgbd_calib import CalibrationConfig, FolderDataset, calibrate, load_board, write_outputs

    if __name__ == "__main__":  # detection runs in worker processes that re-import the script
        dataset = FolderDataset("my_dataset")            # rig.yaml + <camera>/color, depth
        board = load_board("configs/board_thesis.yaml")
        result = calibrate(dataset, board, CalibrationConfig(refine="none"))
        print(result.extrinsics.T_ref_cam("cam8"))       # 4x4, metres, p_ref = T @ p_cam8
        write_outputs(result, dataset.rig, "calib_out")   # extrinsics.yaml, report.html, ...

Every argument that is a path takes a ``str`` or any ``os.PathLike``.

- ``calibrate(dataset: FolderDataset | path, board: Board | path, config: CalibrationConfig |
  None = None, cache_dir: path | None = None, fixed_cameras: dict[str, ndarray] | None = None,
  progress: Progress | None = None) -> CalibrationResult``: the whole pipeline.
- ``check(dataset, calib: Extrinsics | path, ...) -> CheckRun``: has a camera moved since the
  calibration (its ``moved`` and ``unknown`` cameras; ``result.to_dict()`` is check.json).
- ``refine(dataset, init: Extrinsics | path, ...) -> RefineResult``: depth-only refinement;
  ``write_refine(result, out_dir)`` writes its folder as ``rgbd-calib refine`` does.
- ``convert(sources, out, ...) -> ConversionReport``: recordings or one video per camera into
  a dataset folder.
- ``FolderDataset(path)``, ``load_board(path)`` / ``thesis_board()``, ``load_rig(path)``,
  ``CalibrationConfig(**settings)`` / ``load_config(path)``: the inputs (docs/formats.md).
- ``write_outputs(result, rig, out_dir) -> list[Path]``: every output file, atomically.
- ``load_extrinsics(path) -> Extrinsics``: read an ``extrinsics.yaml`` back (its ``verdict``:
  a ``Verdict(grade, reason)``, grade good / check / poor; an unknown camera name raises
  ``UnknownCameraError``, a ``KeyError`` too, listing the cameras).
- ``synthesize(out, layout, n_frames, seed, board, params)``, ``SynthParams``,
  ``load_ground_truth(dataset)``: synthetic rigs with ground truth.
- ``load_depth_models(calib_dir) -> dict[str, DepthModel]`` and ``correct_depth_image(model,
  depth, intrinsics)``: each camera's depth model from ``depth_model.yaml``, applied to a depth
  image aligned to colour (for live pipelines).
- ``RgbdCalibError``: the base of every error a user can cause (one line: what, which file,
  what to do).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> module that defines it (imported on first access)
_API = {
    "calibrate": "pipelines.calibrate",
    "CalibrationResult": "pipelines.calibrate",
    "check": "pipelines.check",
    "CheckRun": "pipelines.check",
    "refine": "pipelines.refine",
    "RefineResult": "pipelines.refine",
    "write_refine": "outputs.writer",
    "convert": "sources.dispatch",
    "CalibrationConfig": "core.config",
    "load_config": "core.config",
    "FolderDataset": "model.dataset",
    "Board": "model.board",
    "load_board": "model.board_file",
    "thesis_board": "model.board",
    "Rig": "model.rig",
    "load_rig": "model.rig",
    "Extrinsics": "model.results",
    "load_extrinsics": "model.results",
    "Verdict": "model.results",
    "write_outputs": "outputs.writer",
    "write_exports": "outputs.exports",
    "synthesize": "synth.render",
    "SynthParams": "synth.render",
    "load_ground_truth": "synth.render",
    "RgbdCalibError": "core.errors",
    "UnknownCameraError": "core.errors",
    "DepthModel": "core.depth_model",
    "correct_depth_image": "core.depth_model",
    "load_depth_models": "model.depth_model_file",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'rgbd_calib' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

