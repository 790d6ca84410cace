"""rgbd-calib: extrinsic calibration of multi-camera RGB-D rigs with a double-sided ArUco board.

The library API (names load on first use, so ``import rgbd_calib`` stays light)::

    from rgbd_calib import CalibrationConfig, FolderDataset, calibrate, load_board, write_outputs

    if __name__ == "__main__":  # detection runs in worker processes that re-import the script
        dataset = FolderDataset("my_dataset")            # rig.yaml + <camera>/color, depth
        board = load_board("configs/board_thesis.yaml")
        result = calibrate(dataset, board, CalibrationConfig(refine="none"))
        print(result.extrinsics.T_ref_cam("cam8"))       # 4x4, metres, p_ref = T @ p_cam8
        write_outputs(result, dataset.rig, "calib_out")   # extrinsics.yaml, report.html, ...

- ``calibrate(dataset: FolderDataset, board: Board, config: CalibrationConfig | None = None,
  cache_dir: Path | None = None, fixed_cameras: dict[str, ndarray] | None = None,
  progress: Progress | None = None) -> CalibrationResult``: the whole pipeline.
  ``rgbd_calib.calibrate`` is also the pipeline's module (``from rgbd_calib.calibrate import
  detect_dataset`` keeps working); calling it calls the function.
- ``FolderDataset(path)``, ``load_board(path)`` / ``thesis_board()``, ``load_rig(path)``,
  ``CalibrationConfig(**settings)`` / ``load_config(path)``: the inputs (docs/formats.md).
- ``write_outputs(result, rig, out_dir) -> list[Path]``: every output file, atomically.
- ``load_extrinsics(path) -> Extrinsics``: read an ``extrinsics.yaml`` back.
- ``synthesize(out, layout, n_frames, seed, board, params)``, ``SynthParams``,
  ``load_ground_truth(dataset)``: synthetic rigs with ground truth.
- ``RgbdCalibError``: the base of every error a user can cause (one line: what, which file,
  what to do).
"""

from __future__ import annotations

import importlib
import types
from typing import Any

__version__ = "0.1.0"

# public name -> module that defines it (imported on first access)
_API = {
    "calibrate": "calibrate",
    "CalibrationResult": "calibrate",
    "CalibrationConfig": "config",
    "load_config": "config",
    "FolderDataset": "dataset",
    "Board": "board",
    "load_board": "board",
    "thesis_board": "board",
    "Rig": "rig",
    "load_rig": "rig",
    "Extrinsics": "results",
    "load_extrinsics": "results",
    "write_outputs": "outputs",
    "write_exports": "exports",
    "synthesize": "synth",
    "SynthParams": "synth",
    "load_ground_truth": "synth",
    "RgbdCalibError": "errors",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'rgbd_calib' has no attribute {name!r}")
    loaded = importlib.import_module(f".{module}", __name__)
    if name == module:  # rgbd_calib.calibrate: the (callable) module itself
        return loaded
    value = getattr(loaded, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


class CallableModule(types.ModuleType):
    """A module that, called, calls its function of the same name: ``rgbd_calib.calibrate``
    is the pipeline's module (for ``import rgbd_calib.calibrate`` and ``from
    rgbd_calib.calibrate import ...``) and, as the README's API, the ``calibrate`` function."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return getattr(self, self.__name__.rpartition(".")[2])(*args, **kwargs)
