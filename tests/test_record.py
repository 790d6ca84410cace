"""record: live capture into the folder form, with a fake device at the DeviceSource boundary."""

from __future__ import annotations

import os
import signal

import cv2
import numpy as np
import pytest

import rgbd_calib.model.dataset as dataset_module
import rgbd_calib.sources.record as record_module
from rgbd_calib.cli.console import cli_record
from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.errors import DatasetError
from rgbd_calib.core.interrupts import raise_if_interrupted, sigint_noted
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.sources.record import CapturedFrame, record

PERIOD_MS = 1000.0 / 30.0


def _marker_image(board, width: int, height: int, ids: list[int], side_px: int) -> np.ndarray:
    """White image with the given board markers (each in a white quiet zone)."""
    img = np.full((height, width), 255, np.uint8)
    for k, marker_id in enumerate(ids):
        marker = cv2.aruco.generateImageMarker(board.aruco_dict, marker_id, side_px)
        x, y = side_px // 2 + k * 2 * side_px, side_px // 2
        img[y : y + side_px, x : x + side_px] = marker
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


class FakeStream:
    def __init__(self, serial, intrinsics, colors, rng, lag_frames=0, interrupt_at=None):
        self.serial = serial
        self.intrinsics = intrinsics
        self.colors = colors
        self.depths = [
            rng.integers(0, 8000, (intrinsics.height, intrinsics.width), dtype=np.uint16)
            for _ in colors
        ]
        self.lag_frames = lag_frames
        self.interrupt_at = interrupt_at
        self.waits = 0
        self.stopped = False
        self.delivered: list[int] = []  # frame index of every frame handed out

    def wait(self, timeout_ms: int) -> CapturedFrame:
        k = self.waits
        self.waits += 1
        if self.interrupt_at is not None and k == self.interrupt_at:
            raise KeyboardInterrupt  # what Ctrl-C does inside pipeline.wait_for_frames
        i = k % len(self.colors)
        self.delivered.append(i)
        return CapturedFrame(
            self.colors[i], self.depths[i], 1000.0 + (k - self.lag_frames) * PERIOD_MS
        )

    def stop(self) -> None:
        self.stopped = True


class FakeSource:
    """Stands in for rs.context + rs.pipeline: the only place tests reach into."""

    def __init__(self, streams):
        self.streams = {s.serial: s for s in streams}
        self.sync_modes: dict[str, int] = {}

    def serials(self) -> list[str]:
        return list(self.streams)

    def open(self, serial, mode, sync_mode):
        assert mode[:2] == (
            self.streams[serial].intrinsics.width,
            self.streams[serial].intrinsics.height,
        )
        self.sync_modes[serial] = sync_mode
        return self.streams[serial]


@pytest.fixture
def board():
    return thesis_board()


def _fake_rig(board, rng, **stream_kwargs) -> FakeSource:
    """Two 640x360 cameras: 'A' sees board markers 0-3, 'B' markers 4-5; a third colour
    frame of each camera has none."""
    streams = []
    for serial, ids in (("A", [0, 1, 2, 3]), ("B", [4, 5])):
        intr = CameraIntrinsics(
            640, 360, 320.0 + len(ids), 320.0, 319.5, 179.5, (0.01, -0.02, 0.0, 0.0, 0.001), 0.001
        )
        colors = [
            _marker_image(board, 640, 360, ids, 60),
            _marker_image(board, 640, 360, ids[:1], 60),
            np.full((360, 640, 3), 200, np.uint8),
        ]
        streams.append(FakeStream(serial, intr, colors, rng, **stream_kwargs.get(serial, {})))
    return FakeSource(streams)


def test_records_n_sets_in_the_folder_form(board, rng, tmp_path):
    source = _fake_rig(board, rng)
    statuses = []
    report = record(
        tmp_path / "set",
        n_sets=3,
        mode=(640, 360, 30),
        board=board,
        device_source=source,
        status_callback=statuses.append,
    )
    assert report.sets_written == 3 and not report.interrupted
    ds = FolderDataset(tmp_path / "set")
    assert ds.cameras == ["A", "B"] and ds.frames == ["000000", "000001", "000002"]
    for name, stream in source.streams.items():
        assert ds.rig.cameras[name] == stream.intrinsics  # rig.yaml from the device
        for stem, i in zip(ds.frames, stream.delivered):
            np.testing.assert_array_equal(ds.read_color(name, stem), stream.colors[i])
            np.testing.assert_array_equal(ds.read_depth(name, stem), stream.depths[i])
        assert stream.stopped
    assert [s.markers for s in statuses] == [{"A": 4, "B": 2}, {"A": 1, "B": 1}, {"A": 0, "B": 0}]
    assert source.sync_modes == {"A": 0, "B": 0}


def test_marker_count_on_downscaled_large_images(board):
    counter = record_module.MarkerCounter(board)
    assert counter(_marker_image(board, 1920, 1080, [7, 8, 9], 150)) == 3


def test_ctrl_c_midway_leaves_only_complete_sets(board, rng, tmp_path):
    source = _fake_rig(board, rng, B={"interrupt_at": 2})  # B's third frame never comes
    report = record(tmp_path / "set", n_sets=None, mode=(640, 360, 30), device_source=source)
    assert report.interrupted and report.sets_written == 2
    ds = FolderDataset(tmp_path / "set")
    assert ds.frames == ["000000", "000001"]
    for cam in ("A", "B"):
        for kind in ("color", "depth"):
            assert sorted(p.name for p in (tmp_path / "set" / cam / kind).iterdir()) == [
                "000000.png",
                "000001.png",
            ]  # no temporary or half files
    assert all(s.stopped for s in source.streams.values())


def test_ctrl_c_that_stops_a_recording_does_not_stop_the_command(board, rng, tmp_path):
    """Under the command's Ctrl-C handler (the CLI's), a real SIGINT that ends an open-ended
    recording is the recording's stop: the command goes on (writes its summary), it is not
    taken for an interrupt a library swallowed."""
    source = _fake_rig(board, rng)
    stream = source.streams["B"]
    real_wait = stream.wait

    def wait_then_sigint(timeout_ms):
        if stream.waits == 2:
            os.kill(os.getpid(), signal.SIGINT)
        return real_wait(timeout_ms)

    stream.wait = wait_then_sigint
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is not at Python's default handler in this process")
    with sigint_noted():
        report = record(tmp_path / "set", n_sets=None, mode=(640, 360, 30),
                        device_source=source)
        raise_if_interrupted()  # the next stage begins
    assert report.interrupted and report.sets_written == 2


def test_ctrl_c_during_the_renames_finishes_the_set(board, rng, tmp_path, monkeypatch):
    real_replace = os.replace
    calls = []

    def replace_then_sigint(src, dst):
        if str(dst).endswith(".png"):  # not rig.yaml's atomic write
            calls.append(dst)
            if len(calls) == 1:
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C arrives between two renames
        real_replace(src, dst)

    monkeypatch.setattr(dataset_module.os, "replace", replace_then_sigint)
    report = record(
        tmp_path / "set", n_sets=None, mode=(640, 360, 30), device_source=_fake_rig(board, rng)
    )
    assert report.interrupted and report.sets_written == 1
    assert len(calls) == 4  # colour + depth of both cameras
    ds = FolderDataset(tmp_path / "set")
    assert ds.frames == ["000000"]
    assert all(ds.depth_path(c, "000000") is not None for c in ("A", "B"))


def test_hardware_sync_makes_the_first_camera_master(board, rng, tmp_path):
    source = _fake_rig(board, rng)
    record(
        tmp_path / "set", n_sets=1, mode=(640, 360, 30), hardware_sync=True, device_source=source
    )
    assert source.sync_modes == {"A": 1, "B": 2}


def test_free_running_cameras_are_brought_together(board, rng, tmp_path):
    source = _fake_rig(board, rng, B={"lag_frames": 2})  # B's first frames are 67 ms old
    statuses = []
    record(
        tmp_path / "set",
        n_sets=2,
        mode=(640, 360, 30),
        device_source=source,
        status_callback=statuses.append,
    )
    assert all(s.spread_ms <= PERIOD_MS / 2 for s in statuses)
    assert source.streams["B"].waits == source.streams["A"].waits + 2


def test_no_camera_is_one_clear_error(tmp_path):
    with pytest.raises(DatasetError) as exc:
        record(tmp_path / "set", n_sets=1, device_source=FakeSource([]))
    assert str(exc.value).startswith("no RealSense camera connected;")
    assert "\n" not in str(exc.value)
    assert not (tmp_path / "set").exists()


def test_refuses_a_non_empty_output_folder(board, rng, tmp_path):
    (tmp_path / "set").mkdir()
    (tmp_path / "set" / "old.txt").write_text("keep me")
    with pytest.raises(DatasetError, match="not empty"):
        record(tmp_path / "set", n_sets=1, mode=(640, 360, 30), device_source=_fake_rig(board, rng))
    assert (tmp_path / "set" / "old.txt").read_text() == "keep me"


def test_cli_record_reports_what_it_wrote(board, rng, tmp_path, capsys):
    report = cli_record(
        tmp_path / "set",
        n_sets=2,
        mode=(640, 360, 30),
        board=board,
        device_source=_fake_rig(board, rng),
    )
    assert report.sets_written == 2
    err = capsys.readouterr().err.replace("\n", " ")
    assert "done: 2 set(s) of 2 camera(s)" in err
    assert "hold the board still" in err  # no --hardware-sync: the time advice
