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

A continuous recording (``params.burst`` > 1) holds each sampled board position for ``burst``
consecutive frame sets, ``1000 / params.frame_rate`` ms apart (30 fps unless given), the board
moving along one trajectory through them: constant linear acceleration ``a`` and angular
acceleration ``alpha`` (about the turn's own axis) per position, so set ``f``'s twist is the
trajectory's at ``t_f``, and within the set ``T_ref_board(t_f + tau) = [Exp_SO3(w_f tau + alpha
tau^2 / 2) R_f | p_f + v_f tau + a tau^2 / 2]`` (exact: the axis is fixed). The sampled pose is
the board's at the middle of its burst. Without acceleration (the default) the twist is
constant over the burst.

A timed render also writes each camera's ``timestamps.csv`` (docs/formats.md), as a recording
has: camera ``c``'s colour frame of set ``f`` is stamped ``t_f + offset_c + jitter`` ms, where
position ``j``'s ``k``-th set is at ``t_f = j * POSITION_PERIOD_MS + k * frame_period_ms``
(a new position each second, close-up positions continuing the count) and the jitter is
Gaussian with sigma ``params.timestamp_jitter_ms`` (:func:`draw_timestamps_ms`): the stamps'
error, not the truth.

Each draw comes from a seeded stream of its own, so switching time on changes no other draw of
the render (rig, board poses, noise)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry import pose_after_twist
from .params import SynthParams, SynthRig

MOTION_STREAM = 0x7157  # rng stream of the board twists (seed, stream)
SYNC_STREAM = 0x5C0C  # rng stream of the cameras' clock offsets (seed, stream)
STAMP_STREAM = 0x57A4  # rng stream of the timestamps' jitter (seed, stream)
ACCEL_STREAM = 0xACCE  # rng stream of the board's accelerations (seed, stream)
POSITION_PERIOD_MS = 1000.0  # one board position (burst) per second


@dataclass(frozen=True)
class SynthTiming:
    """The time truth of a render: per camera (rig order) its clock offset and colour readout
    (seconds), per frame set the board's twist in the reference frame (``v_mps`` and
    ``w_radps``, each ``(F, 3)``), its accelerations (``a_mps2``, ``alpha_radps2``, ``(F, 3)``,
    zero unless ``params.acceleration``), the set's nominal time ``t_ms`` (F,), ``burst``,
    the consecutive sets per board position, and ``frame_period_ms``, their spacing."""

    offset_s: tuple[float, ...]
    readout_s: tuple[float, ...]
    v_mps: np.ndarray
    w_radps: np.ndarray
    a_mps2: np.ndarray
    alpha_radps2: np.ndarray
    t_ms: np.ndarray
    burst: int = 1
    frame_period_ms: float = 1000.0 / 30.0

    def moving(self, frame: int) -> bool:
        """Whether the board moves during frame set ``frame``."""
        return bool(np.any(self.v_mps[frame] != 0) or np.any(self.w_radps[frame] != 0)
                    or np.any(self.a_mps2[frame] != 0) or np.any(self.alpha_radps2[frame] != 0))

    def T_ref_board(self, frame: int, T_ref_centre: np.ndarray) -> np.ndarray:
        """Frame set ``frame``'s board pose at its nominal time, on the trajectory through its
        position's sampled pose ``T_ref_centre`` (the pose at the middle of the burst)."""
        s = self.burst_s(frame)
        a, alpha = self.a_mps2[frame], self.alpha_radps2[frame]
        # the twist at the middle of the burst: this set's with the acceleration undone
        v0, w0 = self.v_mps[frame] - a * s, self.w_radps[frame] - alpha * s
        return pose_after_twist(T_ref_centre, v0, w0, s, a, alpha)

    def burst_s(self, frame: int) -> float:
        """Frame set ``frame``'s time after the middle of its burst (s)."""
        k = frame % self.burst
        return (k - (self.burst - 1) / 2.0) * self.frame_period_ms / 1000.0


def draw_timing(rig: SynthRig, n_positions: int, seed: int, params: SynthParams) -> SynthTiming:
    """The seeded time truth of a render of ``n_positions`` board positions, each held for
    ``params.burst`` frame sets.

    At each position's middle ``v`` is a random direction (uniform on the sphere) times the
    speed of ``params.motion``, ``w`` a random axis times its turn rate; both unit vectors are
    drawn whatever the settings (stream :data:`MOTION_STREAM`), so a faster board moves the
    same way. With ``params.acceleration`` (m/s^2, deg/s^2) the linear acceleration has a
    random direction of its own and the angular one a random sign about ``w``'s axis (stream
    :data:`ACCEL_STREAM`). Every non-reference camera's offset is uniform in
    ``+-params.sync_offset_ms`` (stream :data:`SYNC_STREAM`, one draw per camera in rig order;
    the reference's is 0). Every colour camera reads out in ``params.rolling_shutter_ms``."""
    speed_mps, rate_dps = params.motion
    accel_mps2, accel_dps2 = params.acceleration
    burst = params.burst
    period_ms = 1000.0 / params.frame_rate
    units = np.random.default_rng([seed, MOTION_STREAM]).normal(size=(n_positions, 2, 3))
    units /= np.linalg.norm(units, axis=2, keepdims=True)
    unit_offsets = np.random.default_rng([seed, SYNC_STREAM]).uniform(-1, 1, len(rig.cameras))
    unit_offsets[rig.reference_index] = 0.0
    n = len(rig.cameras)
    a = np.zeros((n_positions, 3))
    alpha = np.zeros((n_positions, 3))
    if accel_mps2 or accel_dps2:
        rng = np.random.default_rng([seed, ACCEL_STREAM])
        a_unit = rng.normal(size=(n_positions, 3))
        a = a_unit / np.linalg.norm(a_unit, axis=1, keepdims=True) * accel_mps2
        sign = rng.choice([-1.0, 1.0], size=n_positions)
        alpha = units[:, 1] * (sign * np.radians(accel_dps2))[:, None]
    s = (np.arange(burst) - (burst - 1) / 2.0) * period_ms / 1000.0  # (burst,)
    rep = np.repeat(np.arange(n_positions), burst)
    s_f = np.tile(s, n_positions)
    v = units[rep, 0] * speed_mps + a[rep] * s_f[:, None]
    w = units[rep, 1] * np.radians(rate_dps) + alpha[rep] * s_f[:, None]
    t_ms = rep * POSITION_PERIOD_MS + np.tile(np.arange(burst), n_positions) * period_ms
    return SynthTiming(
        tuple(float(u) * params.sync_offset_ms / 1000.0 for u in unit_offsets),
        (params.rolling_shutter_ms / 1000.0,) * n,
        v, w, a[rep], alpha[rep], t_ms, burst, period_ms,
    )


def draw_timestamps_ms(timing: SynthTiming, seed: int, params: SynthParams) -> np.ndarray:
    """``(F, C)``: the ``timestamps.csv`` time (ms) of every camera's (rig order) colour frame
    of every frame set, ``t_f + offset_c + jitter``; the jitter is Gaussian
    with sigma ``params.timestamp_jitter_ms``, one draw per set and camera in that order from
    stream :data:`STAMP_STREAM` (drawn for dropped frames too, so drops change no stamp)."""
    n_sets = len(timing.v_mps)
    offsets_ms = 1000.0 * np.asarray(timing.offset_s)
    unit = np.random.default_rng([seed, STAMP_STREAM]).normal(size=(n_sets, len(offsets_ms)))
    return timing.t_ms[:, None] + offsets_ms[None, :] + params.timestamp_jitter_ms * unit


def row_time_s(v_px: float | np.ndarray, height: int, offset_s: float, readout_s: float):
    """When pixel row ``v_px`` (0 = top row; fractional rows give the same linear time) of a
    camera with this ``offset_s`` and colour ``readout_s`` is exposed, relative to ``t_f``."""
    line_delay_s = readout_s / (height - 1) if height > 1 else 0.0
    return offset_s + line_delay_s * (np.asarray(v_px, float) - (height - 1) / 2)
