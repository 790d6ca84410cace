"""Per-camera frame timestamps (``<camera>/timestamps.csv``, docs/formats.md; issue 32 item 2):
``convert`` and ``record`` keep the recording's frame times, FolderWriter writes them and
FolderDataset reads them lazily; a malformed file is one clear line; a folder without them
reads as before.

The recordings are those of tests/test_convert.py (its writers and small synthetic rig):
RealSense SDK ``.db3`` files whose colour frames carry given ``global_time`` timestamps, a
realsense-ros ROS 1 bag with given header stamps, the shared real D435 ``.bag`` (its colour
timestamp read back with librealsense's own playback), one video per camera with a Caliscope
timestamps CSV; ``record`` runs against test_record.py's fake devices.
"""

from __future__ import annotations

import csv
import shutil

import cv2
import numpy as np
import pytest
from test_convert import (
    REAL_BAG,
    _ros_cameras,
    _times,
    needs_real_bag,
    play_real_bag,
    synth_rig,  # noqa: F401 - the module fixture the recordings are made of
    write_ros_bag,
    write_sdk_db3,
)
from test_record import FakeSource, FakeStream, _fake_rig

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.errors import DatasetError
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import (
    TIMESTAMPS_FILE,
    FolderDataset,
    FolderWriter,
    read_timestamps_csv,
)
from rgbd_calib.model.rig import Rig
from rgbd_calib.sources import convert
from rgbd_calib.sources.record import CapturedFrame, record
from rgbd_calib.sources.staging import StagedCamera
from rgbd_calib.sources.sync import clock_notes, shared_clock
from rgbd_calib.sources.video import convert_videos

rs = pytest.importorskip("pyrealsense2")

# librealsense keeps a frame's timestamp as a double (ms): it comes back as given. ROS header
# stamps are integer nanoseconds (the bag writer rounds the ms to ns) and a time of 1.7e12 ms
# is a double with a 2.4e-4 ms spacing: sec * 1e3 + nanosec * 1e-6 is within 1e-3 ms
SDK_ATOL_MS = 1e-6
ROS_ATOL_MS = 1e-3


def _expected(times_ms: list[float], stems: list[str]) -> dict[str, float]:
    return dict(zip(stems, times_ms, strict=True))


def _assert_times(got: dict[str, float] | None, want: dict[str, float], atol_ms: float) -> None:
    assert got is not None, "no timestamps.csv"
    assert sorted(got) == sorted(want)
    for frame, t in want.items():
        assert got[frame] == pytest.approx(t, abs=atol_ms), frame


# --------------------------------------------------------------------------- convert
def test_sdk_recordings_keep_their_colour_timestamps(synth_rig, tmp_path):  # noqa: F811
    """Three cameras' .db3 files 0, 3 and 6 ms apart: each camera's timestamps.csv holds its
    own colour frames' librealsense timestamps (not the reference's), one row per frame."""
    paths, times = [], {}
    for k, (name, intr, frames) in enumerate(synth_rig):
        paths.append(tmp_path / f"{name}.db3")
        times[f"90000{k}"] = _times(len(frames), 3.0 * k)
        write_sdk_db3(paths[-1], f"90000{k}", intr, frames, times[f"90000{k}"])
    report = convert(paths, tmp_path / "out", sync_tolerance_ms=10.0)
    ds = FolderDataset(tmp_path / "out")
    assert report.notes == []
    for serial in report.cameras:
        _assert_times(ds.timestamps_ms(serial), _expected(times[serial], ds.frames),
                      SDK_ATOL_MS)
    # the cameras' times of one set differ by the recordings' offsets (3 ms apart)
    t = {c: ds.timestamps_ms(c) for c in report.cameras}
    for frame in ds.frames:
        assert t["900001"][frame] - t["900000"][frame] == pytest.approx(3.0, abs=SDK_ATOL_MS)


def test_ros_bag_keeps_the_header_stamps(synth_rig, tmp_path):  # noqa: F811
    """A ROS 1 bag of three cameras 2 ms apart, one camera missing a frame: the stamps of
    the frames each camera has, under the stems convert gave them."""
    namespaces = ["/cam_left", "/cam_mid", "/cam_right"]
    cams = _ros_cameras(synth_rig, namespaces, drop=0)  # cam_mid lacks the first frame
    write_ros_bag(tmp_path / "rig.bag", cams, ros1=True)
    report = convert([tmp_path / "rig.bag"], tmp_path / "out")
    ds = FolderDataset(tmp_path / "out")
    for name, ns in zip(report.cameras, namespaces, strict=True):
        stems = [f for f in ds.frames if ds.color_path(name, f) is not None]
        assert len(stems) == len(cams[ns]["times_ms"])
        _assert_times(ds.timestamps_ms(name), _expected(cams[ns]["times_ms"], stems),
                      ROS_ATOL_MS)
    assert ds.timestamps_ms("cam_mid") != ds.timestamps_ms("cam_left")


@needs_real_bag
def test_real_bag_timestamp_is_librealsenses(tmp_path):
    """The shared D435 recording: the converted frame's time is the colour frame's
    timestamp as librealsense's own playback gives it."""
    def use(_profile, frames):
        color = frames.get_color_frame()
        return (float(color.get_timestamp()),
                str(color.get_frame_timestamp_domain()).split(".")[-1])

    t_ms, domain = play_real_bag(use)
    report = convert([REAL_BAG], tmp_path / "out")
    (serial,) = report.cameras
    got = FolderDataset(tmp_path / "out").timestamps_ms(serial)
    assert domain != "hardware_clock" or len(report.cameras) == 1
    _assert_times(got, {"000000": t_ms}, SDK_ATOL_MS)


def test_videos_with_a_timestamps_csv_keep_frame_time(tmp_path):
    """Two videos and a Caliscope timestamps CSV (frame_time in seconds, cam_2's frames 7 ms
    after cam_0's): each kept frame's time is its row's frame_time in ms; without the CSV no
    camera gets a timestamps.csv."""
    rng = np.random.default_rng(5)
    n, fps = 4, 6.0
    rows = []
    for cam_id in (0, 2):
        path = tmp_path / f"cam_{cam_id}.avi"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48))
        assert writer.isOpened()
        for k in range(n):
            writer.write(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
            rows.append((k + 10, cam_id, k, 1234.5 + k / fps + 0.007 * (cam_id == 2)))
        writer.release()
    with open(tmp_path / "timestamps.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["sync_index", "cam_id", "frame_index", "frame_time"])
        w.writerows(rows)
    videos = [tmp_path / "cam_0.avi", tmp_path / "cam_2.avi"]
    convert_videos(videos, tmp_path / "out", timestamps=tmp_path / "timestamps.csv")
    ds = FolderDataset(tmp_path / "out")
    for cam_id in (0, 2):
        want = {f"{s:06d}": 1000.0 * t for s, c, _, t in rows if c == cam_id}
        _assert_times(ds.timestamps_ms(f"cam_{cam_id}"), want, 1e-9)
    convert_videos(videos, tmp_path / "plain")
    plain = FolderDataset(tmp_path / "plain")
    assert plain.timestamps_ms("cam_0") is None and plain.timestamps_ms("cam_2") is None


def _staged(name: str, domain: str) -> StagedCamera:
    cam = StagedCamera(key=f"{name}.bag", name=name)
    cam.timestamp_domain = domain
    return cam


def test_hardware_clocks_of_several_cameras_share_no_clock():
    """Cameras on their own hardware clocks: not one clock (no timestamps.csv, a note says
    so); one camera, global or system time, ROS stamps: one clock."""
    assert not shared_clock([_staged("a", "global_time"), _staged("b", "hardware_clock")])
    assert "no timestamps.csv" in clock_notes([_staged("a", "hardware_clock"),
                                               _staged("b", "hardware_clock")])[0]
    assert shared_clock([_staged("a", "hardware_clock")])
    assert shared_clock([_staged("a", "global_time"), _staged("b", "system_time"),
                         _staged("c", "ros header stamp")])


# --------------------------------------------------------------------------- record
def test_record_writes_each_sets_colour_timestamps(rng, tmp_path):
    """Two fake cameras, 3 sets: each camera's timestamps.csv has the device timestamp of
    the colour frame written in each set."""
    source = _fake_rig(thesis_board(), rng)
    record(tmp_path / "set", n_sets=3, mode=(640, 360, 30), device_source=source)
    ds = FolderDataset(tmp_path / "set")
    for name in ("A", "B"):
        want = {f"{k:06d}": 1000.0 + k * 1000.0 / 30.0 for k in range(3)}
        _assert_times(ds.timestamps_ms(name), want, 1e-9)


class _HardwareClockStream(FakeStream):
    def wait(self, timeout_ms: int) -> CapturedFrame:
        f = super().wait(timeout_ms)
        return CapturedFrame(f.color, f.depth, f.timestamp_ms, "hardware_clock")


def test_record_on_hardware_clocks_writes_no_timestamps(rng, tmp_path):
    intr = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
    colors = [np.full((48, 64, 3), 100, np.uint8)]
    source = FakeSource([_HardwareClockStream(s, intr, colors, rng) for s in ("A", "B")])
    record(tmp_path / "set", n_sets=2, mode=(64, 48, 30), device_source=source)
    ds = FolderDataset(tmp_path / "set")
    assert ds.frames == ["000000", "000001"]
    assert ds.timestamps_ms("A") is None and ds.timestamps_ms("B") is None


# --------------------------------------------------------------------------- the folder form
def _rig() -> Rig:
    intr = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    return Rig({"a": intr, "b": intr}, "a")


def _image(value: int) -> np.ndarray:
    return np.full((24, 32, 3), value, np.uint8)


def test_folder_writer_round_trip(tmp_path):
    """Times written set by set (write_set) and whole (write_timestamps) read back exactly;
    a set without times leaves the file as it was; rows only for frames the camera has."""
    writer = FolderWriter(tmp_path, _rig(), depth_cameras=[])
    t_a = {"000000": 1712345678901.2345, "000001": 1712345678934.5678}
    for k, frame in enumerate(t_a):
        writer.write_set(frame, {"a": _image(k), "b": _image(k)}, {},
                         {"a": t_a[frame], "b": t_a[frame] + 0.125})
    writer.write_set("000002", {"a": _image(2)}, {})  # no times for this set
    ds = FolderDataset(tmp_path)
    assert ds.timestamps_ms("a") == t_a  # exact: written with repr precision
    assert ds.timestamps_ms("b") == {f: t + 0.125 for f, t in t_a.items()}
    assert not list(tmp_path.rglob(".*.tmp"))
    # whole-camera writing adds to what the writer wrote
    writer.write_timestamps("a", {"000002": -3.5})
    assert FolderDataset(tmp_path).timestamps_ms("a") == {**t_a, "000002": -3.5}
    # a row of a frame the camera has no image of is not returned
    (tmp_path / "b" / "color" / "000001.png").unlink()
    assert FolderDataset(tmp_path).timestamps_ms("b") == {"000000": t_a["000000"] + 0.125}


def test_a_failed_set_writes_no_times(tmp_path, monkeypatch):
    """write_set stays all or nothing: an image that cannot be encoded leaves neither its
    files nor its times, and the next set's file does not carry them."""
    import rgbd_calib.model.dataset as dataset_module

    writer = FolderWriter(tmp_path, _rig(), depth_cameras=[])
    writer.write_set("000000", {"a": _image(0)}, {}, {"a": 10.0})
    real = dataset_module.encode_png

    def broken(image, where):
        raise DatasetError(f"{where}: could not encode the image as PNG")

    monkeypatch.setattr(dataset_module, "encode_png", broken)
    with pytest.raises(DatasetError):
        writer.write_set("000001", {"a": _image(1)}, {}, {"a": 20.0})
    monkeypatch.setattr(dataset_module, "encode_png", real)
    assert FolderDataset(tmp_path).timestamps_ms("a") == {"000000": 10.0}
    writer.write_set("000002", {"a": _image(2)}, {}, {"a": 30.0})
    assert FolderDataset(tmp_path).timestamps_ms("a") == {"000000": 10.0, "000002": 30.0}


@pytest.mark.parametrize(
    ("text", "line", "says"),
    [
        ("", 1, "header must be 'frame,t_ms'"),
        ("frame,time\n000000,1.0\n", 1, "header must be 'frame,t_ms'"),
        ("frame,t_ms\n000000,1.0\n000001\n", 3, "expected 'frame,t_ms'"),
        ("frame,t_ms\n000000,1.0,2.0\n", 2, "expected 'frame,t_ms'"),
        ("frame,t_ms\n000000,soon\n", 2, "not a finite number"),
        ("frame,t_ms\n000000,nan\n", 2, "not a finite number"),
        ("frame,t_ms\n000000,1.0\n\n000000,2.0\n", 4, "listed twice"),
    ],
)
def test_a_malformed_file_is_one_line_naming_file_and_line(tmp_path, text, line, says):
    writer = FolderWriter(tmp_path, _rig(), depth_cameras=[])
    writer.write_set("000000", {"a": _image(0), "b": _image(0)}, {})
    path = tmp_path / "a" / TIMESTAMPS_FILE
    path.write_text(text)
    ds = FolderDataset(tmp_path)  # read lazily: opening the folder does not read it
    with pytest.raises(DatasetError) as err:
        ds.timestamps_ms("a")
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: line {line}: ") and says in message, message
    assert "frame" in message.split(";")[-1]  # the fix says what a row must be
    assert ds.timestamps_ms("b") is None  # the other camera is unaffected
    with pytest.raises(DatasetError, match="no camera 'c'"):
        ds.timestamps_ms("c")


def test_a_folder_without_timestamps_reads_as_before(tmp_path):
    """The same folder with and without its timestamps.csv files: frames, sets, summary and
    images identical; timestamps None."""
    writer = FolderWriter(tmp_path / "with", _rig(), depth_cameras=["a"])
    for k in range(3):
        depth = np.full((24, 32), 1000 + k, np.uint16)
        writer.write_set(f"{k:06d}", {"a": _image(k), "b": _image(k + 5)}, {"a": depth},
                         {"a": 100.0 * k, "b": 100.0 * k + 1})
    shutil.copytree(tmp_path / "with", tmp_path / "without")
    for cam in ("a", "b"):
        (tmp_path / "without" / cam / TIMESTAMPS_FILE).unlink()
    with_, without = FolderDataset(tmp_path / "with"), FolderDataset(tmp_path / "without")
    assert with_.timestamps_ms("a") is not None
    assert without.timestamps_ms("a") is None and without.timestamps_ms("b") is None
    assert without.frames == with_.frames
    assert without.summary() == with_.summary()
    assert ([(s.frame, sorted(s.color), sorted(s.depth)) for s in without.frame_sets()]
            == [(s.frame, sorted(s.color), sorted(s.depth)) for s in with_.frame_sets()])
    for f in with_.frames:
        np.testing.assert_array_equal(without.read_color("b", f), with_.read_color("b", f))
    without.check_images()


def test_read_timestamps_csv_tolerates_spaces_and_crlf(tmp_path):
    path = tmp_path / TIMESTAMPS_FILE
    path.write_bytes(b"frame, t_ms\r\n000000, 12.5\r\n000001,13\r\n")
    assert read_timestamps_csv(path) == {"000000": 12.5, "000001": 13.0}
