"""One executor interface (issue 17, item 3): the local process pool by default, a Dask
distributed cluster with ``--scheduler`` / config ``scheduler``. The cluster here is a
2-worker ``LocalCluster`` of processes (the workers unpickle every job and run each
initializer in their own process, as remote ones do). Same detections, same detection cache,
bit-identical pair registrations and extrinsics as the local pool; Ctrl-C cancels; an
unreachable scheduler is one line and writes nothing."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from distributed import Client, LocalCluster
from typer.testing import CliRunner

import rgbd_calib.core.parallel as parallel
from rgbd_calib.cli.commands import app
from rgbd_calib.core.config import DepthConfig, DetectionConfig, load_config
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.parallel import DaskExecutor, executor
from rgbd_calib.detect.run import detect_dataset
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.synth.render import load_ground_truth

runner = CliRunner()
# a port nobody listens on, and a short wait for it: the one-line error comes in ~1 s
UNREACHABLE = "tcp://127.0.0.1:9"


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0", silence_logs=50) as c:
        yield c.scheduler_address


def test_detection_on_dask_equals_the_local_pool_and_its_cache(tiny_dataset, cluster,
                                                               tmp_path):
    ds = FolderDataset(tiny_dataset)
    board, config = thesis_board(), DetectionConfig()
    local = detect_dataset(ds, board, config, tmp_path / "local.json", workers=2)
    remote = detect_dataset(ds, board, config, tmp_path / "dask.json", scheduler=cluster)
    assert len(local) == 16 and local.keys() == remote.keys()
    for key in local:
        assert local[key].to_dict() == remote[key].to_dict(), key
    # the parent writes the cache, the same bytes either way
    assert (tmp_path / "local.json").read_bytes() == (tmp_path / "dask.json").read_bytes()


def test_pair_registrations_on_dask_are_bit_identical_to_the_local_pool(tiny_dataset, cluster):
    from rgbd_calib.depth.clouds import static_cloud
    from rgbd_calib.depth.registration import find_overlapping_pairs
    from rgbd_calib.depth.stage import register_pairs

    ds = FolderDataset(tiny_dataset)
    T = load_ground_truth(tiny_dataset).T_ref_cam
    config = DepthConfig(voxel_schedule_m=[0.04, 0.02], iterations=[20, 10])  # quicker
    clouds = {c: static_cloud(ds, c, {}, T[c], None, config) for c in ("cam7", "cam8", "cam9")}
    overlaps = find_overlapping_pairs(clouds, T, {c: ds.rig.cameras[c] for c in clouds},
                                      config)[:2]
    assert len(overlaps) == 2
    jobs = [(o.cam_a, o.cam_b, T[o.cam_a], T[o.cam_b], (False, False)) for o in overlaps]
    local = register_pairs(clouds, jobs, "colored-icp", config, workers=2)
    remote = register_pairs(clouds, jobs, "colored-icp", config, scheduler=cluster)
    for a, b in zip(local, remote):
        assert (a.cam_a, a.cam_b, a.accepted) == (b.cam_a, b.cam_b, b.accepted)
        assert np.array_equal(a.T_b_a, b.T_b_a)
        assert np.array_equal(a.information, b.information)


def test_static_clouds_in_threads_and_on_dask_equal_the_ones_made_one_at_a_time(
        tiny_dataset, cluster, tmp_path):
    """The depth stage's per-camera clouds: identical points made one at a time, in two
    threads and on the cluster; a camera whose depth cannot be read costs that camera only,
    with its reason."""
    import shutil

    from rgbd_calib.depth.stage import static_clouds

    data = tmp_path / "ds"
    shutil.copytree(tiny_dataset, data)
    for png in (data / "cam9" / "depth").glob("*.png"):
        png.write_bytes(b"not a png")  # cam9's depth unreadable
    ds = FolderDataset(data)
    T = load_ground_truth(data).T_ref_cam
    config = DepthConfig(max_frames=2)
    jobs = [(c, T[c], 1.0) for c in ("cam7", "cam8", "cam9")]
    here = static_clouds(ds, jobs, {}, None, config, workers=1)
    threads = static_clouds(ds, jobs, {}, None, config, workers=2)
    remote = static_clouds(ds, jobs, {}, None, config, scheduler=cluster)
    assert set(here[0]) == {"cam7", "cam8"} and set(here[1]) == {"cam9"}, here[1]
    for clouds, skipped in (threads, remote):
        assert skipped == here[1]
        for c, cloud in here[0].items():
            assert np.array_equal(cloud.points, clouds[c].points), c


def test_calibrate_through_a_cluster_gives_the_same_extrinsics(tiny_calibration, cluster,
                                                               tmp_path):
    dataset, local_out, _ = tiny_calibration
    out = tmp_path / "dask"
    res = runner.invoke(app, ["calibrate", str(dataset), "--out", str(out),
                              "--scheduler", cluster])
    assert res.exit_code == 0, res.output
    assert (out / "extrinsics.yaml").read_text() == (local_out / "extrinsics.yaml").read_text()
    assert load_config(out / "config_resolved.yaml").scheduler == cluster
    report = json.loads((out / "report.json").read_text())
    assert report["pairs"], "the depth stage registered no pair: nothing went through Dask"


def test_depth_models_fitted_in_worker_processes_equal_the_ones_fitted_here(tiny_calibration,
                                                                           tmp_path):
    """The depth stage fits each camera's depth model in its own task: two worker processes
    (tiny_calibration's ``--workers 2``) and one process give the same depth_model.yaml and
    extrinsics, byte for byte."""
    dataset, pooled, _ = tiny_calibration
    out = tmp_path / "here"
    res = runner.invoke(app, ["calibrate", str(dataset), "--out", str(out), "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert (pooled / "depth_model.yaml").is_file()
    for name in ("depth_model.yaml", "extrinsics.yaml"):
        assert (out / name).read_text() == (pooled / name).read_text(), name


def test_initializer_runs_on_every_worker_and_map_keeps_order(tiny_dataset, cluster):
    from rgbd_calib.detect.markers import detect_job, init_detector

    ds = FolderDataset(tiny_dataset)
    jobs = [(c, fs.frame, str(p), ds.rig.cameras[c].width, ds.rig.cameras[c].height)
            for fs in ds.frame_sets() for c, p in fs.color.items()][:9]
    with executor(scheduler=cluster, initializer=init_detector,
                  initargs=(thesis_board(), DetectionConfig())) as ex:
        assert isinstance(ex, DaskExecutor)
        # detect_job reads the board the initializer left in its worker's module state
        got = list(ex.map(detect_job, jobs, chunksize=2))
        assert [(c, f) for c, f, _ in got] == [(c, f) for c, f, *_ in jobs]
        assert sum(len(det["ids"]) for *_, det in got) > 0
        assert ex.submit(divmod, 7, 2).result() == (3, 1)
        with pytest.raises(ZeroDivisionError):
            ex.submit(divmod, 1, 0).result()


def test_leaving_by_ctrl_c_cancels_the_tasks_and_closes_the_client(cluster):
    with pytest.raises(KeyboardInterrupt):
        with executor(scheduler=cluster) as ex:
            # a running task cannot be stopped (Dask cancels what has not started; a thread
            # runs on): short sleeps, so the next test does not wait for them
            futures = [ex.submit(time.sleep, 2) for _ in range(4)]
            raise KeyboardInterrupt
    assert ex._client.status == "closed"
    with Client(cluster, set_as_default=False) as client:
        deadline = time.monotonic() + 10
        while any(client.processing().values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(client.processing().values())
    assert all(f.cancelled() for f in futures)


def test_ctrl_c_during_detection_on_dask_keeps_the_cache_and_cancels(tiny_dataset, cluster,
                                                                     tmp_path):
    ds = FolderDataset(tiny_dataset)
    cache = tmp_path / "detections.json"
    seen = []

    def progress(count):  # Ctrl-C after the 3rd image came back
        seen.append(count)
        if len(seen) > 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        detect_dataset(ds, thesis_board(), DetectionConfig(), cache, progress=progress,
                       scheduler=cluster)
    assert len(json.loads(cache.read_text())["images"]) == 3  # the parent saved what came
    with Client(cluster, set_as_default=False) as client:
        assert not client.who_has()  # no result left on the cluster, no client holding one


@pytest.mark.parametrize("command", ["calibrate", "check", "refine"])
def test_an_unreachable_scheduler_is_one_line_and_writes_nothing(tiny_calibration, tmp_path,
                                                                 monkeypatch, command):
    monkeypatch.setattr(parallel, "CONNECT_TIMEOUT_S", 1.0)
    dataset, calib, _ = tiny_calibration
    out = tmp_path / "out"
    extra = {"calibrate": [], "check": ["--calib", str(calib)],
             "refine": ["--init", str(calib / "extrinsics.yaml")]}[command]
    t0 = time.perf_counter()
    res = runner.invoke(app, [command, str(dataset), "--out", str(out), *extra,
                              "--scheduler", UNREACHABLE])
    assert res.exit_code == 2, res.output
    assert time.perf_counter() - t0 < 10  # the patched 1 s timeout, not the 10 s default
    text = " ".join(res.output.split())
    assert f"--scheduler {UNREACHABLE}: no Dask scheduler answered" in text
    assert "dask scheduler" in text and "Traceback" not in res.output
    assert not out.exists()


def test_a_scheduler_without_workers_is_one_line(monkeypatch):
    monkeypatch.setattr(parallel, "CONNECT_TIMEOUT_S", 1.0)
    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0",
                      silence_logs=50) as empty:
        with pytest.raises(ConfigError, match=r"no worker is connected .* `dask worker "):
            executor(scheduler=empty.scheduler_address)


def test_a_malformed_address_is_one_line():
    with pytest.raises(ConfigError, match=r"^--scheduler foo://h:1: not a Dask scheduler address"):
        parallel.connect("foo://h:1")


def test_without_dask_installed_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "distributed", None)
    with pytest.raises(ConfigError, match=r"rgbd-calib\[dask\]"):
        parallel.connect("tcp://127.0.0.1:8786")


def test_scheduler_config_key_is_validated():
    assert load_config(None, scheduler="tcp://10.0.0.2:8786").scheduler == "tcp://10.0.0.2:8786"
    assert load_config(None).scheduler is None
    with pytest.raises(ConfigError, match=r"^options: scheduler: "):
        load_config(None, scheduler="tcp://host name:8786")


def test_a_pool_broken_before_the_last_submit_is_one_clear_error():
    """A worker that dies early breaks the pool while tasks are still being submitted: that
    submit, a later map and the results of what was in flight all give the one clear error,
    never a BrokenProcessPool traceback (a CI flake of the guard-word test)."""
    import os
    from concurrent.futures.process import BrokenProcessPool

    from rgbd_calib.core.errors import RgbdCalibError

    with parallel.WorkerPool(1) as pool:
        dead = pool.submit(os._exit, 1)
        with pytest.raises(BrokenProcessPool):
            dead.result(timeout=60)
        with pytest.raises(RgbdCalibError, match="a worker process stopped"):
            pool.submit(abs, -1)
        with pytest.raises(RgbdCalibError, match="a worker process stopped"):
            list(pool.map(abs, [1, -2, 3]))
