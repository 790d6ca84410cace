"""A module of ``rgbd_calib`` as it is at another git revision, for before/after profiles
(tools/profile_detection.py, tools/profile_bundle.py)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_module(name: str, path: Path) -> ModuleType:
    """Import the file ``path`` as ``rgbd_calib.<name>`` (its relative imports resolve
    against the installed package)."""
    spec = importlib.util.spec_from_file_location(f"rgbd_calib.{name}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def module_at(rev: str, relpath: str, name: str) -> ModuleType:
    """``relpath`` (e.g. ``rgbd_calib/solve/bundle.py``) at git revision ``rev``, read with
    ``git show`` (the working tree is not touched) and imported as ``rgbd_calib.<name>``
    (``name`` with its package, e.g. ``solve.bundle_baseline``, so that its relative imports
    resolve)."""
    text = subprocess.run(
        ["git", "show", f"{rev}:{relpath}"], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{name}.py"
        path.write_text(text)
        return load_module(name, path)
