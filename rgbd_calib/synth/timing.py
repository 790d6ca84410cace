"""Time in a synthetic render (docs/synthetic.md, "Time"): the board's motion during each frame
set, each camera's clock offset and its colour sensor's rolling-shutter readout.

The shared convention (docs/formats.md, "Synthetic ground truth"): frame set ``f`` has a
nominal time ``t_f``, at which ``ground_truth.yaml``'s ``T_ref_board[f]`` holds. The board
moves with a constant twist over the set, its linear velocity ``v_f`` (m/s) and angular velocity
``w_f`` (rad/s) both in the reference frame, the rotation about the board origin::

    T_ref_board(t_f + tau) = [Exp_SO3(w_f tau) R_f | p_f + v_f tau]

Camera ``c`` exposes set ``f`` at ``t_f + offset_c`` (the reference camera's offset is 0); a
rolling-shutter colour image exposes pixel row ``y`` (0 = top) at
``t_f + offset_c + line_delay_c (y - (H - 1) / 2)`` with ``line_delay_c = readout_c / (H - 1)``,
so the middle of the image is at ``t_f + offset_c``; the (global-shutter) depth image is exposed
as a whole at ``t_f + offset_c``.

A timed render also writes each camera's ``timestamps.csv`` (docs/formats.md), as a recording
has: camera ``c``'s colour frame of set ``f`` is stamped ``t_f + offset_c + jitter`` ms, the
frame sets taken as consecutive captures at a nominal 30 fps (``t_f = f * 1000 / 30`` ms,
close-up sets continuing the count) and the jitter Gaussian with sigma
``params.timestamp_jitter_ms`` (:func:`draw_timestamps_ms`): the stamps' error, not the truth.

Each draw comes from a seeded stream of its own, so switching time on changes no other draw of
the render (rig, board poses, noise)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import SynthParams, SynthRig

MOTION_STREAM = 0x7157  # rng stream of the board twists (seed, stream)
SYNC_STREAM = 0x5C0C  # rng stream of the cameras' clock offsets (seed, stream)
STAMP_STREAM = 0x57A4  # rng stream of the timestamps' jitter (seed, stream)
FRAME_PERIOD_MS = 1000.0 / 30.0  # frame set f is captured at t_f = f * FRAME_PERIOD_MS


@dataclass(frozen=True)
class SynthTiming:
    """The time truth of a render: per camera (rig order) its clock offset and colour readout
    (seconds), per frame set the board's twist in the reference frame (``v_mps`` and
    ``w_radps``, each ``(F, 3)``)."""

    offset_s: tuple[float, ...]
    readout_s: tuple[float, ...]
    v_mps: np.ndarray
    w_radps: np.ndarray

    def moving(self, frame: int) -> bool:
        """Whether the board moves during frame set ``frame``."""
        return bool(np.any(self.v_mps[frame] != 0) or np.any(self.w_radps[frame] != 0))


def draw_timing(rig: SynthRig, n_sets: int, seed: int, params: SynthParams) -> SynthTiming:
    """The seeded time truth of a render of ``n_sets`` frame sets.

    ``v_f`` is a random direction (uniform on the sphere) times the speed of ``params.motion``,
    ``w_f`` a random axis times its turn rate; both unit vectors are drawn whatever the
    settings (stream :data:`MOTION_STREAM`), so a faster board moves the same way. Every
    non-reference camera's offset is uniform in ``+-params.sync_offset_ms`` (stream
    :data:`SYNC_STREAM`, one draw per camera in rig order; the reference's is 0). Every colour
    camera reads out in ``params.rolling_shutter_ms``."""
    speed_mps, rate_dps = params.motion
    units = np.random.default_rng([seed, MOTION_STREAM]).normal(size=(n_sets, 2, 3))
    units /= np.linalg.norm(units, axis=2, keepdims=True)
    unit_offsets = np.random.default_rng([seed, SYNC_STREAM]).uniform(-1, 1, len(rig.cameras))
    unit_offsets[rig.reference_index] = 0.0
    n = len(rig.cameras)
    return SynthTiming(
        tuple(float(u) * params.sync_offset_ms / 1000.0 for u in unit_offsets),
        (params.rolling_shutter_ms / 1000.0,) * n,
        units[:, 0] * speed_mps,
        units[:, 1] * np.radians(rate_dps),
    )


def draw_timestamps_ms(timing: SynthTiming, seed: int, params: SynthParams) -> np.ndarray:
    """``(F, C)``: the ``timestamps.csv`` time (ms) of every camera's (rig order) colour frame
    of every frame set, ``f * FRAME_PERIOD_MS + offset_c + jitter``; the jitter is Gaussian
    with sigma ``params.timestamp_jitter_ms``, one draw per set and camera in that order from
    stream :data:`STAMP_STREAM` (drawn for dropped frames too, so drops change no stamp)."""
    n_sets = len(timing.v_mps)
    t_f = np.arange(n_sets) * FRAME_PERIOD_MS
    offsets_ms = 1000.0 * np.asarray(timing.offset_s)
    unit = np.random.default_rng([seed, STAMP_STREAM]).normal(size=(n_sets, len(offsets_ms)))
    return t_f[:, None] + offsets_ms[None, :] + params.timestamp_jitter_ms * unit


def row_time_s(v_px: float | np.ndarray, height: int, offset_s: float, readout_s: float):
    """When pixel row ``v_px`` (0 = top row; fractional rows give the same linear time) of a
    camera with this ``offset_s`` and colour ``readout_s`` is exposed, relative to ``t_f``."""
    line_delay_s = readout_s / (height - 1) if height > 1 else 0.0
    return offset_s + line_delay_s * (np.asarray(v_px, float) - (height - 1) / 2)
