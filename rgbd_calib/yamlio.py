"""Small YAML helpers shared by the loaders: safe reads with one-line errors, atomic writes."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import ConfigError


def read_yaml_mapping(path: Path, what: str) -> dict[str, Any]:
    """Read a YAML file that must hold a mapping; every failure is one ConfigError line."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: {what} not found; check the path")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" (line {line + 1})" if line is not None else ""
        raise ConfigError(f"{path}: not valid YAML{where}; fix the {what} syntax") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: {what} must be a YAML mapping, got {type(data).__name__}")
    return data


def check_keys(mapping: dict[str, Any], allowed: set[str], where: str, required=()) -> None:
    """Reject unknown keys (typos) and missing required keys with one clear line."""
    unknown = sorted(set(map(str, mapping)) - allowed)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}"
        )
    missing = [k for k in required if k not in mapping]
    if missing:
        raise ConfigError(f"{where}: missing required key(s) {', '.join(missing)}")


def matrix4(value: Any, where: str) -> np.ndarray:
    """Parse a nested-list 4x4 matrix (formats.md ``<4x4>``)."""
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: expected a 4x4 matrix of numbers") from exc
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(f"{where}: expected a finite 4x4 matrix, got shape {T.shape}")
    return T


def to_builtin(obj: Any) -> Any:
    """Convert numpy scalars/arrays (recursively) to plain Python for YAML/JSON dumps."""
    if isinstance(obj, dict):
        return {str(k): to_builtin(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_builtin(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_builtin(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path`` and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_yaml(path: Path, data: Any) -> None:
    atomic_write_text(path, yaml.safe_dump(to_builtin(data), sort_keys=False, width=100))
