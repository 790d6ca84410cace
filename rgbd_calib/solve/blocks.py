"""The self-calibration's model blocks: what each group of parameters the ladder can free
adds to the bundle adjustment (pure; no solve).

A block owns, in one place:

- ``config_update``: the ``bundle`` settings that switch it on (explicit modes, never
  ``auto``); off, its settings hold the files' values;
- ``parameters``: how many parameters it adds to a rig (the BIC's ``k``,
  :func:`rgbd_calib.solve.selfcal.compare`);
- ``held``: why a solve that freed it held it anyway (the data cannot move it), or None;
- ``label``: its part of a model's name in the report (``time + board + fx fy cx cy``).

Its variables, priors and factors are built by :mod:`rgbd_calib.solve.bundle` from those
settings (the back sheet and faces: :mod:`.bundle_faces`; the lens: :mod:`.bundle_factors`;
time: :mod:`.time_model`). The ladder (:mod:`.ladder`) frees blocks by evidence and asks each
for its count and its held test.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

BACK_SHEET_PARAMETERS = 4  # in-plane offset (2), rotation about the normal, thickness
FACE_PARAMETERS = 6  # a multi-face target's face: a full pose


@dataclass(frozen=True)
class RigShape:
    """What a block's parameter count depends on: the cameras a solve has (``cameras``), those
    whose pose it frees (``free_cameras``: not held by ``--fix``), its frame-set views, and the
    board (its ``sheets``: a multi-face target's faces)."""

    cameras: int
    free_cameras: int
    views: int
    board: Any


class ModelBlock(Protocol):
    label: str

    def config_update(self) -> dict[str, Any]: ...

    def parameters(self, rig: RigShape) -> int: ...

    def held(self, result: Any) -> str | None: ...


@dataclass(frozen=True)
class BoardBlock:
    """The target's own geometry: a double-sided board's back sheet (in-plane offset, rotation
    about the normal, thickness), or each non-reference face of a multi-face target (a pose)."""

    label: str = "board"

    def config_update(self) -> dict[str, Any]:
        return {"board": "refine"}

    def parameters(self, rig: RigShape) -> int:
        sheets = rig.board.sheets
        return FACE_PARAMETERS * (len(sheets) - 1) if sheets else BACK_SHEET_PARAMETERS

    def held(self, result: Any) -> str | None:
        """The back sheet held (no view shows both faces), or every face held."""
        if result.board is not None and result.board.held:
            return str(result.board.held)
        if result.faces and all(f.held for f in result.faces):
            return "; ".join(f.held for f in result.faces)
        return None


@dataclass(frozen=True)
class IntrinsicsBlock:
    """Per camera the intrinsics ``params`` (``fx fy cx cy``, and the lens's coefficients when
    it frees them) under a prior at rig.yaml's values."""

    params: tuple[str, ...]

    @property
    def label(self) -> str:
        return " ".join(self.params)

    def config_update(self) -> dict[str, Any]:
        return {"intrinsics": "refine", "intrinsics_params": list(self.params)}

    def parameters(self, rig: RigShape) -> int:
        return len(self.params) * rig.free_cameras

    def held(self, result: Any) -> str | None:
        return None


@dataclass(frozen=True)
class TimeBlock:
    """Per camera a clock offset and a rolling-shutter readout (the reference's offset held),
    per frame set the board's twist (:mod:`.time_model`)."""

    label: str = "time"

    def config_update(self) -> dict[str, Any]:
        return {"time": "refine"}

    def parameters(self, rig: RigShape) -> int:
        return 2 * rig.cameras - 1 + 6 * rig.views

    def held(self, result: Any) -> str | None:
        return None


OFF: dict[str, Any] = {"board": "fixed", "intrinsics": "fixed", "time": "fixed"}


def added(before: tuple[ModelBlock, ...], after: tuple[ModelBlock, ...], rig: RigShape) -> int:
    """The parameters ``after``'s blocks add to ``before``'s: each new block's count, and for
    intrinsics the parameters it frees beyond those already free."""
    total = 0
    own = {type(b): b for b in before}
    for block in after:
        prior = own.get(type(block))
        if prior is None:
            total += block.parameters(rig)
        elif isinstance(block, IntrinsicsBlock) and isinstance(prior, IntrinsicsBlock):
            total += (len(block.params) - len(prior.params)) * rig.free_cameras
    return total


def newly_held(before: tuple[ModelBlock, ...], after: tuple[ModelBlock, ...],
               result: Any) -> str | None:
    """Why a block ``after`` frees beyond ``before`` was held in ``result`` anyway, or None."""
    kinds = {type(b) for b in before}
    for block in after:
        if type(block) not in kinds:
            reason = block.held(result)
            if reason:
                return reason
    return None
