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


# modules the scripts import, not scripts themselves
TOOL_LIBRARIES = {"baseline.py", "peers.py", "toolmain.py"}
SCRIPTS = sorted(p.name for p in (REPO / "tools").glob("*.py") if p.name not in TOOL_LIBRARIES)


def test_every_script_in_tools_is_a_script_or_a_named_library():
    """A tool without ``__main__`` is one of the named libraries; a script has one (so the
    --help test below reaches every script: a tool that no longer imports is found here, not
    by its next user)."""
    for name in SCRIPTS:
        assert '__name__ == "__main__"' in (REPO / "tools" / name).read_text(), name
    assert len(SCRIPTS) >= 25


def test_every_tool_answers_help(tmp_path):
    """Each script imports against today's package and parses its arguments: ``--help``
    prints its usage and exits 0 (one process runs them all, so the suite pays one import)."""
    code = (
        "import runpy, sys\n"
        f"sys.path.insert(0, {str(REPO / 'tools')!r})\n"
        "bad = []\n"
        f"for name in {SCRIPTS!r}:\n"
        f"    sys.argv = [name, '--help']\n"
        "    try:\n"
        f"        runpy.run_path({str(REPO / 'tools')!r} + '/' + name, run_name='__main__')\n"
        "        bad.append((name, 'no exit'))\n"
        "    except SystemExit as exc:\n"
        "        if exc.code not in (0, None):\n"
        "            bad.append((name, exc.code))\n"
        "    except Exception as exc:\n"
        "        bad.append((name, repr(exc)))\n"
        "print('BAD', bad)\n"
    )
    done = _run("-c", code, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "BAD []" in done.stdout, done.stdout[-3000:]
    assert done.stdout.count("usage:") >= len(SCRIPTS), done.stdout[-3000:]


def test_the_floor_bench_on_a_missing_or_wrong_folder_is_one_line_and_exit_2(tmp_path):
    """tools/bench_floor.py (issue 59 item 4): a folder that is not there, and one that is no
    dataset, each one line naming it, exit 2, before any work."""
    (tmp_path / "empty").mkdir()
    for folder in ("nowhere", "empty"):
        done = _run(str(REPO / "tools" / "bench_floor.py"), str(tmp_path / folder),
                    cwd=tmp_path)
        assert done.returncode == 2, done.stderr
        assert "Traceback" not in done.stderr
        last = done.stderr.strip().splitlines()[-1]
        assert last.startswith("error: bench_floor.py: ") and folder in last, last
