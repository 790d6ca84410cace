"""Ctrl-C at the exact moments that matter, sent by the code under test itself (deterministic,
unlike a signal from outside): while the outputs are renamed into place, and after they are.
The end-to-end Ctrl-C runs are in tests/test_robustness.py."""

from __future__ import annotations

import os
import signal

import pytest
import typer

from rgbd_calib.core import interrupts
from rgbd_calib.model.dataset import staged_folder
from rgbd_calib.outputs import writer as outputs


@pytest.fixture(autouse=True)
def _fresh_commit_record(monkeypatch):
    monkeypatch.setattr(interrupts, "_COMMITTED", [])
    monkeypatch.setattr(interrupts, "_PENDING", [])


def _default_sigint():
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is not at Python's default handler in this process")


def _swallowed_ctrl_c():
    """A real SIGINT that lands inside a weakref callback, as during a figure's garbage
    collection: Python prints "Exception ignored" and goes on."""
    import weakref

    class Thing:
        pass

    def callback(_ref):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # the handler runs here, inside the callback
            pass

    thing = Thing()
    ref = weakref.ref(thing, callback)
    del thing
    assert ref() is None


def _earlier(out):
    out.mkdir()
    for name in ("report.json", "extrinsics.yaml", "report.html"):
        (out / name).write_text(f"earlier {name}\n")


def _files(out) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(out.iterdir()) if p.is_file()}


def test_ctrl_c_during_the_renames_waits_for_the_last_one(tmp_path, monkeypatch):
    """SIGINT on the first rename: every file is renamed all the same, then the interrupt is
    raised; the folder holds the new run whole and is recorded as complete."""
    out = tmp_path / "out"
    _earlier(out)
    # the handler before (SIG_IGN where the run was started in the background by a shell)
    handler = signal.getsignal(signal.SIGINT)
    real_replace = os.replace
    calls = []

    def replace_then_interrupt(src, dst):
        calls.append(dst)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGINT)  # lands now, during the renames
        real_replace(src, dst)

    monkeypatch.setattr(outputs.os, "replace", replace_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        with outputs.staged(out, replaces=("report.html",)) as stage:
            for name in ("extrinsics.yaml", "report.json", "config_resolved.yaml"):
                (stage / name).write_text(f"new {name}\n")
    assert len(calls) == 3 and calls[-1].name == "extrinsics.yaml"
    assert _files(out) == {n: f"new {n}\n" for n in
                           ("config_resolved.yaml", "extrinsics.yaml", "report.json")}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    assert interrupts.committed() == (out,)
    assert signal.getsignal(signal.SIGINT) is handler  # restored


def test_ctrl_c_before_the_renames_leaves_the_earlier_results(tmp_path):
    out = tmp_path / "out"
    _earlier(out)
    before = _files(out)
    with pytest.raises(KeyboardInterrupt):
        with outputs.staged(out, replaces=("report.html",)) as stage:
            (stage / "extrinsics.yaml").write_text("new\n")
            raise KeyboardInterrupt
    assert _files(out) == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    assert interrupts.committed() == ()


def test_ctrl_c_while_a_dataset_folder_is_published(tmp_path, monkeypatch):
    """The convert / synth folder: renamed whole, then the interrupt."""
    out = tmp_path / "set"
    real_rename = type(out).rename

    def rename_then_interrupt(self, target):
        os.kill(os.getpid(), signal.SIGINT)
        return real_rename(self, target)

    monkeypatch.setattr(type(out), "rename", rename_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        with staged_folder(out) as tmp:
            (tmp / "rig.yaml").write_text("cameras: {}\n")
    assert (out / "rig.yaml").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["set"]
    assert interrupts.committed() == (out,)


@pytest.mark.parametrize("written", [False, True])
def test_the_interrupt_line_says_whether_the_results_were_written(tmp_path, capsys, written):
    from rgbd_calib.cli.commands import user_errors

    out = tmp_path / "out [1]"  # brackets: printed as text, not rich markup

    @user_errors
    def command():
        if written:
            interrupts.mark_committed(out)
        raise KeyboardInterrupt

    with pytest.raises(typer.Exit) as exc:
        command()
    assert exc.value.exit_code == 130
    text = " ".join(capsys.readouterr().err.split())
    if written:
        assert text == (f"interrupted after the results were written: {out} complete; "
                        "nothing to run again")
    else:
        assert text == ("interrupted: earlier results were left untouched; run the same "
                        "command again to finish")


def test_ctrl_c_while_the_static_clouds_are_built_drops_the_cameras_not_started(monkeypatch):
    """The clouds are built in threads: a Ctrl-C stops the stage after the cameras in hand,
    the others are never started (not waited for one by one)."""
    import threading
    import time

    import numpy as np

    from rgbd_calib.core.config import DepthConfig
    from rgbd_calib.depth import stage

    started = []
    lock = threading.Lock()

    def slow_cloud(dataset, camera, *args):
        with lock:
            started.append(camera)
        time.sleep(0.2)
        return None, "fake"

    monkeypatch.setattr(stage, "_cloud_job", slow_cloud)
    jobs = [(f"cam{i}", np.eye(4), 1.0) for i in range(20)]

    def tick(count):
        raise KeyboardInterrupt  # after the first camera came back

    with pytest.raises(KeyboardInterrupt):
        stage.static_clouds(None, jobs, {}, None, DepthConfig(), workers=2, tick=tick)
    assert len(started) <= 4, started  # the first two, and at most the two that followed


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_swallowed_ctrl_c_stops_the_next_stage_and_the_command(capsys):
    """A Ctrl-C that a library swallowed does not let the command run on to exit 0: the next
    stage does not begin, and the command ends as interrupted (130, the usual line)."""
    from rgbd_calib.cli.commands import user_errors
    from rgbd_calib.core.progress import timed

    _default_sigint()
    stages = []

    @user_errors
    def command():
        with timed({}, "first"):
            _swallowed_ctrl_c()
            stages.append("first went on")
        with timed({}, "second"):
            stages.append("second")

    with pytest.raises(typer.Exit) as exc:
        command()
    assert exc.value.exit_code == 130
    assert stages == ["first went on"]
    assert "interrupted: earlier results were left untouched" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored

    @user_errors
    def swallowed_at_the_end():
        with timed({}, "only"):
            _swallowed_ctrl_c()

    with pytest.raises(typer.Exit) as exc:
        swallowed_at_the_end()
    assert exc.value.exit_code == 130


def test_outside_a_command_a_caught_ctrl_c_is_not_raised_again():
    """A library caller (a notebook) that catches the interrupt itself runs on unhindered."""
    from rgbd_calib.core.progress import timed

    _default_sigint()
    with pytest.raises(KeyboardInterrupt):
        with interrupts.sigint_deferred():
            os.kill(os.getpid(), signal.SIGINT)
    with timed({}, "next"):
        pass
