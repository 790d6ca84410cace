"""One error family for every user-facing failure.

The CLI prints ``str(error)`` as a single line and exits non-zero; messages therefore say
what is wrong, which file, and what to do.
"""

from __future__ import annotations


class RgbdCalibError(Exception):
    """Base class of every error a user can cause (bad files, bad options, bad data)."""


class ConfigError(RgbdCalibError):
    """A YAML/CSV/config file is malformed or inconsistent."""


class BoardError(ConfigError):
    """A board definition is invalid (duplicate ids, mirrored winding, ...)."""


class DatasetError(RgbdCalibError):
    """A recorded dataset folder is unreadable or inconsistent with its rig.yaml."""


class CalibrationError(RgbdCalibError):
    """Nothing valid can be calibrated from the given data."""
