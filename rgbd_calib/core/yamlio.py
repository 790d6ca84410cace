"""Small YAML helpers shared by the loaders: safe reads with one-line errors, atomic writes."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import ConfigError


class _DuplicateKeyError(yaml.constructor.ConstructorError):
    def __init__(self, key: Any, mark: Any):
        super().__init__(None, None, f"duplicate key {key!r}", mark)
        self.key = key


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that rejects a key given twice in one mapping (PyYAML silently
    keeps the last one: a camera pasted twice into rig.yaml would win without a word)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # unhashable: the base class reports it
                    continue
                if duplicate:
                    raise _DuplicateKeyError(key, key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


def read_yaml_mapping(path: Path, what: str) -> dict[str, Any]:
    """Read a YAML file that must hold a mapping; every failure is one ConfigError line."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: {what} not found; check the path")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text; is this the {what}?") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from exc
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # a SafeLoader subclass
    except _DuplicateKeyError as exc:
        line = exc.problem_mark.line + 1 if exc.problem_mark else "?"
        raise ConfigError(
            f"{path}: key {exc.key!r} appears twice in one mapping (line {line}); "
            f"keep one in the {what}"
        ) from exc
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" (line {line + 1})" if line is not None else ""
        raise ConfigError(f"{path}: not valid YAML{where}; fix the {what} syntax") from exc
    if not isinstance(data, dict):
        raise ConfigError(
            f"{path}: {what} must be a YAML mapping, got {type(data).__name__}; "
            "use the layout of docs/formats.md"
        )
    return data


def shown(key: Any) -> str:
    """A user-written key for a one-line message (``repr`` when it holds control characters)."""
    text = str(key)
    return text if text.isprintable() else repr(text)


def check_keys(mapping: dict[str, Any], allowed: set[str], where: str, required=()) -> None:
    """Reject unknown keys (typos) and missing required keys with one clear line."""
    unknown = sorted(shown(k) for k in set(map(str, mapping)) - allowed)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)}; use one of {', '.join(sorted(allowed))}"
        )
    missing = [k for k in required if k not in mapping]
    if missing:
        raise ConfigError(f"{where}: missing required key(s) {', '.join(missing)}; add them")


def matrix4(value: Any, where: str) -> np.ndarray:
    """Parse a nested-list 4x4 matrix (formats.md ``<4x4>``)."""
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ConfigError(f"{where}: expected a 4x4 matrix of numbers; give 4 rows of 4") from exc
    if T.shape != (4, 4):
        raise ConfigError(f"{where}: expected a 4x4 matrix, got shape {T.shape}; give 4 rows of 4")
    if not np.all(np.isfinite(T)):
        raise ConfigError(f"{where}: the 4x4 matrix holds NaN or infinite values; fix it")
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
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_yaml(path: Path, data: Any, header: str = "") -> None:
    """Write ``data`` as YAML atomically, after ``header`` (each line made a ``#`` comment)."""
    comment = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    atomic_write_text(path, comment + yaml.safe_dump(to_builtin(data), sort_keys=False,
                                                     width=100))
