"""The settings a user tunes, apart from the expert ones: the ``user:`` section of a config
file and of ``config_resolved.yaml`` (docs/guide.md, "Settings").

A config file may give any of :data:`USER_SETTINGS` in its ``user:`` section by their short
name (``intrinsics: fixed``) or at their place among the stages' settings
(``bundle: {intrinsics: fixed}``); both at once must agree. ``config_resolved.yaml`` lists the
user section first, then every setting grouped by stage as it always did (the user settings
again at their places, so that readers of the earlier file keep their keys).
Pure dict work: :mod:`rgbd_calib.core.config` validates the result.
"""

from __future__ import annotations

from typing import Any

from .errors import ConfigError

#: short name -> (dotted place among the stages' settings, what it does). Defaults are the
#: stages' own (core/config.py); ``calibrate``'s ``--intrinsics``, ``--time``,
#: ``--board-model``, ``--refine``, ``--method`` and ``--workers`` set the same settings.
USER_SETTINGS: dict[str, tuple[str, str]] = {
    "method": ("method", "bundle (default) or posegraph (the thesis method)"),
    "refine": ("refine", "depth refinement: auto, colored-icp, geometric or none"),
    "intrinsics": ("bundle.intrinsics",
                   "auto: refine fx fy cx cy and the lens where the views ask for it; refine; "
                   "fixed: rig.yaml's"),
    "intrinsics_params": ("bundle.intrinsics_params",
                          "the parameters refine may free (a fisheye's k1..k4 stand for the "
                          "lens names)"),
    "board": ("bundle.board", "the back sheet's / faces' poses: auto, refine or fixed"),
    "time": ("bundle.time", "unsynchronised cameras' clocks and the board's motion: auto, "
             "refine or fixed"),
    "corners": ("detection.refinement", "marker corner refinement: edges (default), subpix, "
                "contour or none"),
    "min_markers": ("pose.min_markers", "markers a view needs for a pose"),
    "depth_model": ("depth.model", "per-camera depth model from the board: auto or none"),
    "overlap_models": ("depth.overlap_models",
                       "update the depth models by the overlapping pairs"),
    "fused_voxel_m": ("depth.fused_voxel_m", "fused.ply's voxel (m)"),
    "workers": ("workers", "detection processes; default all cores"),
}
USER_SECTION = "user"
_MISSING = object()


def _get(data: dict, dotted: str) -> Any:
    node: Any = data
    for key in dotted.split("."):
        if not isinstance(node, dict) or key not in node:
            return _MISSING
        node = node[key]
    return node


def set_dotted(data: dict, dotted: str, value: Any) -> None:
    """Set ``data``'s setting at the dotted place ``"stage.key"`` (its stages made as needed;
    a stage that is not a mapping is left for the validation to name)."""
    *parents, leaf = dotted.split(".")
    node = data
    for key in parents:
        node = node.setdefault(key, {})
        if not isinstance(node, dict):
            return
    node[leaf] = value


def apply_user_section(data: dict, where: str) -> dict:
    """``data`` (a config mapping) with its ``user:`` section moved to the settings' places;
    one-line :class:`ConfigError` for an unknown short name or a setting given twice with
    different values."""
    if USER_SECTION not in data:
        return data
    user = data[USER_SECTION]
    out = {k: v for k, v in data.items() if k != USER_SECTION}
    if user is None:
        return out
    if not isinstance(user, dict):
        raise ConfigError(f"{where}: user: expected a mapping of settings "
                          f"({', '.join(USER_SETTINGS)})")
    for name, value in user.items():
        if name not in USER_SETTINGS:
            raise ConfigError(f"{where}: user.{name}: not a user setting; use one of "
                              f"{', '.join(USER_SETTINGS)}, or give it in its stage's section")
        dotted = USER_SETTINGS[name][0]
        there = _get(out, dotted)
        if there is not _MISSING and there != value:
            raise ConfigError(f"{where}: user.{name} is {value!r} but {dotted} is {there!r}; "
                              "give it once")
        set_dotted(out, dotted, value)
    return out


def split_user_section(data: dict) -> dict:
    """A resolved config mapping as ``config_resolved.yaml`` lists it: ``user:`` first (each
    of :data:`USER_SETTINGS` by its short name), then every setting at its place as before
    (so readers of the earlier file keep their keys; :func:`apply_user_section` takes the
    two when they agree)."""
    user = {name: _get(data, dotted) for name, (dotted, _) in USER_SETTINGS.items()
            if _get(data, dotted) is not _MISSING}
    return {USER_SECTION: user, **data}


def user_section_comments() -> str:
    """The comment block ``config_resolved.yaml`` starts with: what the sections are and
    what each user setting does."""
    lines = ["# rgbd-calib settings (any subset may be given to --config).",
             "# user: the settings a user tunes; below it every setting by stage, for experts",
             "# (docs/guide.md, 'Settings'). Change a user setting in one place: in user:,",
             "# or at its place below; both at once must agree.",
             "#"]
    lines += [f"#   {name}: {what}" for name, (_, what) in USER_SETTINGS.items()]
    return "\n".join(lines) + "\n"
