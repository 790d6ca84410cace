"""The benchmarks in tools/ given bad input end in one line naming the tool and the problem,
with a non-zero exit, not in a traceback (tools/toolmain.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300, check=False)


def test_a_missing_dataset_is_one_line_and_exit_2(tmp_path):
    done = _run(str(REPO / "tools" / "bench_time_cost.py"), str(tmp_path / "nowhere"),
                cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("error: bench_time_cost.py: ") and "nowhere" in last, last


def test_the_edge_offset_bench_on_a_missing_render_is_one_line_and_exit_2(tmp_path):
    done = _run(str(REPO / "tools" / "bench_edge_offset.py"), str(tmp_path / "nowhere"),
                "--work", str(tmp_path / "work"), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("error: bench_edge_offset.py: ") and "nowhere" in last, last


def test_a_failed_step_names_its_log_and_exits_1(tmp_path):
    done = _run(str(REPO / "tools" / "bench_fused.py"), str(tmp_path), "--layouts", "nope",
                cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("error: bench_fused.py: rgbd-calib synth ") and ".log" in last, last
