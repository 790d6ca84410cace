"""Bad input, end to end through the CLI (issue 8).

"A calibration tool that silently returns a wrong rig is worse than one that fails." Every bad
input below is generated here from the small synthetic sets of conftest.py (no binaries in the
repository). Where nothing valid can be produced the command must exit 2 with exactly one line
(what, which file, what to do), no traceback, and leave an earlier result untouched; where a
valid result can still be produced (a stray marker, blurred frames, a camera that never shares
a view, one camera with wrong intrinsics) it must exit 0, be right for the good cameras, and
say what went wrong in report.json.

Every case adds a row to the table of docs/robustness.md; the last test checks that each row
seen in this run is in the doc (``RGBD_CALIB_WRITE_DOCS=1`` rewrites the table instead).

Speed: calibrations run with ``--refine none`` and start from a copy of the clean run's
detection cache, so only the images a case changed are detected again.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import REPO
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.cli.console import PROGRESS_LINE
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.synth.render import load_ground_truth

runner = CliRunner()
RGBD_CALIB = Path(sys.executable).parent / "rgbd-calib"
DOC = REPO / "docs" / "robustness.md"
TABLE_START, TABLE_END = "<!-- robustness-table:start -->", "<!-- robustness-table:end -->"

# small_line has 6 noisy frames: the end-to-end bounds of test_cli.py
E2E_MM, E2E_DEG = 1.0, 0.05
# every one-line error says what to do: a clause after "; " with one of these verbs, or a
# closing question ("is this the dataset folder?")
ADVICE = re.compile(
    r"; (?:[^;]* )?(check|fix|use|add|choose|re-export|record|keep|set|align|export|list|"
    r"move|delete|remove|give|edit|re-run|run|copy|write|rename)\b"
    r"|\?( \(format: docs/formats\.md#[a-z0-9-]+\))?$"  # a question, then the format's section
)

ROWS: dict[str, tuple[str, str, str, str]] = {}  # case -> (input, command, exit, user sees)


# ----------------------------------------------------------------------------- helpers
def cli(*args) -> tuple[int, str]:
    result = runner.invoke(app, [str(a) for a in args])
    if result.exception and not isinstance(result.exception, SystemExit):
        raise result.exception  # a traceback: the test fails and shows it
    return result.exit_code, result.output


def normalize(text: str, *paths: tuple[Path, str]) -> str:
    for path, name in sorted(paths, key=lambda p: -len(str(p[0]))):
        text = text.replace(str(path), name)
    return text


def record(case: str, what: str, command: str, code: int, seen: str) -> None:
    ROWS[case] = (what, command, str(code), seen)


@dataclass(frozen=True)
class Clean:
    """small_line calibrated once (--refine none): its detection cache and result."""

    dataset: Path
    out: Path
    detection_s: float


@pytest.fixture(scope="module")
def clean(small_line, tmp_path_factory) -> Clean:
    out = tmp_path_factory.mktemp("robust") / "clean"
    code, text = cli("calibrate", small_line.path, "--out", out, "--refine", "none")
    assert code == 0, text
    report = json.loads((out / "report.json").read_text())
    return Clean(small_line.path, out, report["timings_s"]["detection"])


@dataclass(frozen=True)
class Work:
    """A copy of the clean dataset to damage, and an output folder holding an earlier
    result (the clean one) and the clean detection cache."""

    root: Path
    ds: Path
    out: Path
    earlier: bytes  # extrinsics.yaml
    earlier_report: bytes

    def norm(self, text: str) -> str:
        return normalize(text, (self.out, "<out>"), (self.ds, "<dataset>"), (self.root, "<tmp>"))


def workspace(clean: Clean, tmp_path: Path, cache: bool = True) -> Work:
    ds, out = tmp_path / "ds", tmp_path / "out"
    shutil.copytree(clean.dataset, ds)  # copy2 keeps mtimes: the cache stays valid
    out.mkdir()
    # an earlier result that no run writes byte for byte (a good run may repeat the clean one)
    (out / "extrinsics.yaml").write_bytes(
        b"# earlier result\n" + (clean.out / "extrinsics.yaml").read_bytes())
    (out / "report.json").write_bytes((clean.out / "report.json").read_bytes() + b"\n")
    if cache:
        (out / "cache").mkdir()
        shutil.copy2(clean.out / "cache" / "detections.json", out / "cache")
    return Work(tmp_path, ds, out, (out / "extrinsics.yaml").read_bytes(),
                (out / "report.json").read_bytes())


def assert_one_line_failure(w: Work, code: int, text: str, names: str | Path,
                            row: tuple[str, str, str] | None = None) -> str:
    """Exit 2, one line naming ``names`` and saying what to do; the earlier result kept.
    ``row`` = (case, input, command) records the case for the doc table first."""
    lines = [ln for ln in text.strip().splitlines() if not PROGRESS_LINE.match(ln)]
    if row is not None:
        record(*row, code, w.norm(" / ".join(lines)))
    assert code == 2, text
    assert "Traceback" not in text
    assert len(lines) == 1, text
    line = lines[0]
    assert line.startswith("error: "), line
    assert str(names) in line, f"{names} not named in: {line}"
    assert ADVICE.search(line), f"no advice in: {line}"
    assert (w.out / "extrinsics.yaml").read_bytes() == w.earlier
    assert (w.out / "report.json").read_bytes() == w.earlier_report
    leftovers = [p.name for p in w.out.iterdir() if p.name.startswith(".")]
    assert not leftovers, leftovers
    return line


def calibrate(w: Work, *extra) -> tuple[int, str]:
    """One process: a handful of changed images detect faster than a pool starts."""
    extra = extra if "--workers" in extra else ("--workers", "1", *extra)
    return cli("calibrate", w.ds, "--out", w.out, "--refine", "none", *extra)


def fail_case(case: str, what: str, w: Work, names, *extra, command: str = "calibrate"):
    if command == "calibrate":
        code, text = calibrate(w, *extra)
        shown = " ".join(["calibrate <dataset>", *(w.norm(str(e)) for e in extra)])
    else:
        code, text = cli(command, *extra)
        shown = w.norm(f"{command} " + " ".join(map(str, extra)))
    return assert_one_line_failure(w, code, text, names, (case, what, shown))


def check_result(w: Work, good: list[str], expect_missing: tuple[str, ...] = ()) -> dict:
    """extrinsics.yaml is new and right for the ``good`` cameras; returns report.json."""
    assert (w.out / "extrinsics.yaml").read_bytes() != w.earlier  # written by this run
    gt = load_ground_truth(w.ds)
    cams = yaml.safe_load((w.out / "extrinsics.yaml").read_text())["cameras"]
    for name in good:
        deg, mm = transform_error(np.asarray(cams[name]["T_ref_cam"]), gt.T_ref_cam[name])
        assert mm < E2E_MM and deg < E2E_DEG, (name, mm, deg)
    for name in expect_missing:
        assert name not in cams
    return json.loads((w.out / "report.json").read_text())


def ok_case(case: str, what: str, w: Work, text: str, listed: str, code: int = 0) -> None:
    """A valid result: exit ``code`` (0, or 3 when its verdict is POOR)."""
    flat = " ".join(text.split())  # the summary lines wrap at the console width
    flat = flat.split(" verdict: ")[0]  # the notes come before the verdict and its warnings
    notes = re.findall(r"not calibrated: .*?(?= not calibrated:| results in |$)", flat)
    seen = "summary table" + "".join(f"; `{w.norm(n)}`" for n in notes)
    record(case, what, "calibrate <dataset>", code, f"{seen}; report.json: {listed}")


# ----------------------------------------------------------------------------- corruptions
def png_chunks(data: bytes):
    i = 8
    while i + 12 <= len(data):
        n = struct.unpack(">I", data[i : i + 4])[0]
        yield i, n, data[i + 4 : i + 8]
        i += 12 + n


def damage_idat(path: Path, fix_crc: bool) -> None:
    """Zero 64 bytes in the middle of the first IDAT chunk (optionally keeping its CRC valid,
    so only the zlib stream is broken)."""
    data = bytearray(path.read_bytes())
    i, n, _ = next(c for c in png_chunks(bytes(data)) if c[2] == b"IDAT")
    data[i + 8 + n // 2 : i + 8 + n // 2 + 64] = bytes(64)
    if fix_crc:
        data[i + 8 + n : i + 12 + n] = struct.pack(">I", zlib.crc32(bytes(data[i + 4 : i + 8 + n])))
    path.write_bytes(bytes(data))


def truncate(path: Path, keep: float = 0.4) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def truncated_jpeg(path: Path) -> Path:
    ok, buf = cv2.imencode(".jpg", cv2.imread(str(path)))
    assert ok
    path.unlink()
    jpg = path.with_suffix(".jpg")
    jpg.write_bytes(buf.tobytes()[: len(buf) // 2])
    return jpg


def rewrite(path: Path, fn) -> None:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert cv2.imwrite(str(path), fn(img))


def edit_rig(ds: Path, fn) -> Path:
    path = ds / "rig.yaml"
    data = yaml.safe_load(path.read_text())
    fn(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def marker_image(marker_id: int, side_px: int) -> np.ndarray:
    """A board marker with a white quiet zone, ``side_px`` wide (border included)."""
    cells = thesis_board().marker_cells(marker_id)
    img = cv2.resize(cells, (side_px, side_px), interpolation=cv2.INTER_NEAREST)
    q = max(side_px // 5, 4)
    return cv2.copyMakeBorder(img, q, q, q, q, cv2.BORDER_CONSTANT, value=255)


def paste(img: np.ndarray, patch: np.ndarray, x: int, y: int) -> np.ndarray:
    h, w = patch.shape[:2]
    img[y : y + h, x : x + w] = patch[..., None] if img.ndim == 3 else patch
    return img


def rename_frames(ds: Path, out: Path, camera: str, prefix: str) -> None:
    """Give ``camera``'s frames stems no other camera has (same images: the cache entries
    move with them)."""
    for kind in ("color", "depth"):
        for p in sorted((ds / camera / kind).iterdir()):
            p.rename(p.with_name(prefix + p.name[1:]))
    cache = out / "cache" / "detections.json"
    data = json.loads(cache.read_text())
    images = {}
    for key, entry in data["images"].items():
        cam, frame = key.split("/")
        images[f"{cam}/{prefix + frame[1:]}" if cam == camera else key] = entry
    data["images"] = images
    cache.write_text(json.dumps(data))


def cached_detections(out: Path) -> dict[tuple[str, str], dict]:
    data = json.loads((out / "cache" / "detections.json").read_text())
    return {tuple(k.split("/")): v["det"] for k, v in data["images"].items()}


# ----------------------------------------------------------------------------- images
def _color(w: Work, cam: str, frame: str) -> Path:
    return w.ds / cam / "color" / f"{frame}.png"


def _depth(w: Work, cam: str, frame: str) -> Path:
    return w.ds / cam / "depth" / f"{frame}.png"


def _truncated_png(w):
    truncate(p := _color(w, "cam8", "000002"))
    return p


def _crc_error(w):
    damage_idat(p := _color(w, "cam8", "000003"), fix_crc=False)
    return p


def _zlib_error(w):
    damage_idat(p := _color(w, "cam9", "000001"), fix_crc=True)
    return p


def _empty_file(w):
    (p := _color(w, "cam7", "000000")).write_bytes(b"")
    return p


def _text_file(w):
    (p := _color(w, "cam7", "000001")).write_text("hello")
    return p


def _depth_8bit(w):
    rewrite(p := _depth(w, "cam8", "000002"), lambda d: (d // 32).astype(np.uint8))
    return p


def _depth_3ch(w):
    rewrite(p := _depth(w, "cam8", "000002"), lambda d: np.dstack([d] * 3))
    return p


def _depth_size(w):
    rewrite(p := _depth(w, "cam10", "000005"),
            lambda d: cv2.resize(d, (640, 360), interpolation=cv2.INTER_NEAREST))
    return p


def _color_size(w):
    edit_rig(w.ds, lambda r: r["cameras"]["cam9"].update(width=1920, height=1080, cx=960.0,
                                                         cy=540.0))
    return _color(w, "cam9", "000000")


def _two_images(w):
    shutil.copy(_color(w, "cam8", "000001"), _color(w, "cam8", "000001").with_suffix(".jpg"))
    return w.ds / "cam8" / "color"


IMAGE_CASES = {
    "truncated colour PNG": _truncated_png,
    "colour PNG with a damaged chunk (CRC error)": _crc_error,
    "colour PNG with damaged compressed data (valid CRC)": _zlib_error,
    "truncated colour JPEG": lambda w: truncated_jpeg(_color(w, "cam8", "000004")),
    "empty colour file": _empty_file,
    "text file named .png": _text_file,
    "8-bit depth": _depth_8bit,
    "3-channel depth": _depth_3ch,
    "depth of another size than colour": _depth_size,
    "colour of another size than rig.yaml": _color_size,
    "two colour images for one frame": _two_images,
}


@pytest.mark.parametrize("case", list(IMAGE_CASES))
def test_bad_image_fails_with_one_line(clean, tmp_path, case):
    w = workspace(clean, tmp_path)
    names = IMAGE_CASES[case](w)
    fail_case(case, case, w, names)


@pytest.mark.parametrize("damage", ["truncate", "zlib"])
def test_no_library_chatter_on_stderr(clean, tmp_path, damage):
    """Run as a user would (a real process, file descriptor 2): libpng/OpenCV must not add
    their own lines to ours."""
    w = workspace(clean, tmp_path)
    bad = w.ds / "cam8" / "color" / "000002.png"
    truncate(bad) if damage == "truncate" else damage_idat(bad, fix_crc=True)
    run = subprocess.run(
        [RGBD_CALIB, "calibrate", w.ds, "--out", w.out, "--refine", "none", "--workers", "1"],
        capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    assert run.stdout == ""
    lines = [ln for ln in run.stderr.strip().splitlines() if not PROGRESS_LINE.match(ln)]
    assert len(lines) == 1 and str(bad) in lines[0], run.stderr


def test_libpng_quiet_keeps_other_output(capfd):
    """The decode's stderr capture drops libpng's own lines only: anything else written to
    file descriptor 2 meanwhile (another thread's progress, a warning) comes out after it."""
    from rgbd_calib.model.dataset import _libpng_quiet

    with _libpng_quiet():
        os.write(2, b"libpng error: bad adaptive filter value\n")
        os.write(2, b"PNG warning: iCCP: known incorrect sRGB profile\n")  # imagecodecs'
        os.write(2, b"other output\n")
    assert capfd.readouterr().err == "other output\n"


def test_decoding_in_threads_leaves_opencv_quiet_only_while_it_decodes(clean, tmp_path, capfd):
    """The depth stage decodes in threads: good and damaged PNGs decoded at once in 4 threads
    give the same pixels as one at a time, the damaged one its one error, no libpng chatter,
    and OpenCV's process-wide log level is restored (it was saved and set per decode; two
    threads interleaving left it silent)."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    from rgbd_calib.core.errors import DatasetError
    from rgbd_calib.model.dataset import read_color_image, read_depth_image

    good = sorted(clean.dataset.glob("cam7/*/*.png"))[:8]
    bad = tmp_path / "bad.png"
    bad.write_bytes(good[0].read_bytes()[:-40])  # truncated

    def read(path):
        try:
            if path.parent.name == "depth":
                return read_depth_image(path, 1280, 720)
            return read_color_image(path, 1280, 720)
        except DatasetError as exc:
            return str(exc)

    paths = (good + [bad]) * 6
    alone = [read(p) for p in paths]
    level = cv2.utils.logging.getLogLevel()
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(read, paths))
    assert cv2.utils.logging.getLogLevel() == level
    for a, b in zip(alone, together):
        assert (a == b) if isinstance(a, str) else np.array_equal(a, b)
    assert sum(isinstance(r, str) and str(bad) in r for r in together) == 6
    assert capfd.readouterr().err == ""


def _png_bytes(layout: str) -> bytes:
    """A small PNG of each layout a user's files may have (PIL writes the ones OpenCV cannot)."""
    import io

    from PIL import Image

    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (21, 34, 3), dtype=np.uint8)
    if layout.startswith("opencv"):
        image = {
            "opencv bgr": rgb,
            "opencv grey": rgb[..., 0],
            "opencv depth": rng.integers(0, 65536, (21, 34), dtype=np.uint16),
            "opencv 16-bit colour": rng.integers(0, 65536, (21, 34, 3), dtype=np.uint16),
        }[layout]
        return cv2.imencode(".png", image)[1].tobytes()
    image = {
        "pil rgba": Image.fromarray(np.dstack([rgb, rgb[..., :1]])),
        "pil palette": Image.fromarray(rgb).quantize(16),
        "pil grey+alpha": Image.fromarray(rgb[..., 0]).convert("LA"),
        "pil 1-bit": Image.fromarray(rgb[..., 0] > 128),
        "pil interlaced": Image.fromarray(rgb),
    }[layout]
    buf = io.BytesIO()
    image.save(buf, format="PNG", interlace=layout == "pil interlaced")
    return buf.getvalue()


@pytest.mark.parametrize(
    "layout",
    ["opencv bgr", "opencv grey", "opencv depth", "opencv 16-bit colour", "pil rgba",
     "pil palette", "pil grey+alpha", "pil 1-bit", "pil interlaced"],
)
@pytest.mark.parametrize("flags", ["IMREAD_COLOR", "IMREAD_GRAYSCALE", "IMREAD_UNCHANGED"])
def test_png_decoding_matches_opencv(tmp_path, layout, flags):
    """The faster PNG path (imagecodecs) gives what cv2.imdecode gives, for every layout and
    read mode; only grey from colour may differ by 1 DN (OpenCV's cvtColor weights, as for an
    image in memory, instead of libpng's own conversion)."""
    from rgbd_calib.model.dataset import _decode

    data = _png_bytes(layout)
    (path := tmp_path / "x.png").write_bytes(data)
    ours = _decode(path, getattr(cv2, flags), "image")
    want = cv2.imdecode(np.frombuffer(data, np.uint8), getattr(cv2, flags))
    assert ours.dtype == want.dtype and ours.shape == want.shape
    grey_from_colour = flags == "IMREAD_GRAYSCALE" and want.ndim == 2 and "grey" not in layout
    grey_from_colour &= layout not in ("opencv depth", "pil 1-bit")
    diff = np.abs(ours.astype(int) - want.astype(int)).max()
    assert diff <= (1 if grey_from_colour else 0)
    if grey_from_colour and layout in ("opencv bgr", "pil rgba", "pil interlaced"):
        # 8-bit colour takes the fast path: grey as for an image in memory (to_gray of BGR)
        from rgbd_calib.detect.markers import to_gray

        colour = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert np.array_equal(ours, to_gray(colour))


# ----------------------------------------------------------------------------- rig.yaml
RIG_CASES = {
    "NaN fx": (lambda r: r["cameras"]["cam8"].update(fx=float("nan")), "cameras.cam8.fx"),
    "zero fy": (lambda r: r["cameras"]["cam8"].update(fy=0), "cameras.cam8.fy"),
    "negative cx": (lambda r: r["cameras"]["cam9"].update(cx=-640.5), "cameras.cam9.cx"),
    "principal point outside the image": (
        lambda r: r["cameras"]["cam9"].update(cy=1000.0), "principal point"),
    "fx given as text": (lambda r: r["cameras"]["cam7"].update(fx="633,4"), "cameras.cam7.fx"),
    "400-digit integer width": (
        lambda r: r["cameras"]["cam7"].update(width=10**400), "cameras.cam7.width"),
    "unknown key in a camera (typo)": (
        lambda r: r["cameras"]["cam10"].update(k1=0.1), "unknown key(s) k1"),
    "unknown top-level key": (lambda r: r.update(refrence="cam8"), "unknown key(s) refrence"),
    "distortion as a string": (
        lambda r: r["cameras"]["cam8"].update(distortion="12345"), "cameras.cam8.distortion"),
    "reference not among the cameras": (lambda r: r.update(reference="cam1"), "'cam1'"),
}


@pytest.mark.parametrize("case", list(RIG_CASES))
def test_bad_rig_fails_with_one_line(clean, tmp_path, case):
    w = workspace(clean, tmp_path)
    mutate, detail = RIG_CASES[case]
    rig = edit_rig(w.ds, mutate)
    line = fail_case(f"rig.yaml: {case}", f"rig.yaml: {case}", w, rig)
    assert detail in line


@pytest.mark.parametrize("case, setup, names", [
    ("camera folder with no rig.yaml entry",
     lambda w: shutil.copytree(w.ds / "cam8", w.ds / "cam11"), "cam11"),
    ("rig.yaml camera with no folder", lambda w: shutil.rmtree(w.ds / "cam9"), "cam9"),
    ("camera listed twice in rig.yaml",
     lambda w: (w.ds / "rig.yaml").write_text(
         (w.ds / "rig.yaml").read_text() + "  cam8: {width: 1280, height: 720, fx: 600, "
         "fy: 600, cx: 640, cy: 360}\n"), "'cam8' appears twice"),
    ("rig.yaml is not YAML (tab indent)",
     lambda w: (w.ds / "rig.yaml").write_text("cameras:\n\tcam7: {}\n"), "rig.yaml"),
    ("rig.yaml is binary", lambda w: (w.ds / "rig.yaml").write_bytes(bytes(range(256))),
     "rig.yaml"),
    ("rig.yaml is a list", lambda w: (w.ds / "rig.yaml").write_text("- cam7\n- cam8\n"),
     "rig.yaml"),
    ("empty dataset (no images)",
     lambda w: [p.unlink() for p in w.ds.glob("*/*/*.png")], "no colour images"),
    ("rig.yaml missing", lambda w: (w.ds / "rig.yaml").unlink(), "rig.yaml"),
])
def test_bad_dataset_layout_fails_with_one_line(clean, tmp_path, case, setup, names):
    w = workspace(clean, tmp_path)
    setup(w)
    fail_case(case, case, w, names)


def test_dataset_path_is_a_file(clean, tmp_path):
    w = workspace(clean, tmp_path)
    archive = tmp_path / "dataset.zip"
    archive.write_bytes(b"PK")
    code, text = cli("calibrate", archive, "--out", w.out)
    assert_one_line_failure(w, code, text, archive, (
        "dataset path is a file", "dataset path is a file", "calibrate <tmp>/dataset.zip"))


def test_hidden_files_are_skipped(clean, tmp_path):
    """macOS leaves ``._000001.png`` (AppleDouble) beside copied images: not an image."""
    w = workspace(clean, tmp_path)
    (w.ds / "cam8" / "color" / "._000001.png").write_bytes(b"\x00\x05\x16\x07")
    (w.ds / "cam8" / "color" / ".DS_Store").write_bytes(b"\x00")
    code, text = calibrate(w)
    assert code == 0, text
    check_result(w, ["cam7", "cam8", "cam9", "cam10"])
    ok_case("hidden files", "hidden files (._000001.png, .DS_Store) in a colour folder", w, text,
            "nothing (skipped)")


# ----------------------------------------------------------------------------- board files
G = "dictionary: DICT_4X4_100\nthickness: 0.0066\n"
SQUARE = "[[0, 0.04, 0], [0.04, 0.04, 0], [0.04, 0, 0], [0, 0, 0]]"
BOARD_CASES = {
    "board: duplicate marker ids": (
        G + f"markers:\n  1: {SQUARE}\n  '1': [[0.1, 0.04, 0], [0.14, 0.04, 0], [0.14, 0, 0], "
        "[0.1, 0, 0]]\n", "duplicate marker id(s) [1]"),
    "board: grid faces overlapping in ids": (
        G + "grid: {rows: 4, cols: 7, marker_length: 0.04, separation: 0.02, front_first_id: 0,"
        " back_first_id: 20}\n", "duplicate marker id(s)"),
    "board: mirrored winding": (
        G + "markers:\n  1: [[0.04, 0.04, 0], [0, 0.04, 0], [0, 0, 0], [0.04, 0, 0]]\n",
        "listed mirrored"),
    "board: ids outside its dictionary": (
        G + "grid: {rows: 4, cols: 7, marker_length: 0.04, separation: 0.02, front_first_id: 0,"
        " back_first_id: 80}\n", "outside the dictionary"),
    "board: unknown key": (
        G + "grid: {rows: 4, cols: 7, marker_length: 0.04, separation: 0.02, front_first_id: 0,"
        " colour: red}\n", "unknown key(s) colour"),
    "board: unknown dictionary": (
        "dictionary: DICT_9X9_1\nthickness: 0.0066\ngrid: {rows: 4, cols: 7, marker_length: 0.04,"
        " separation: 0.02, front_first_id: 0}\n", "DICT_9X9_1"),
    "board: markers given as a list": (G + "markers: [1, 2]\n", "[[x,y,z], ...]"),
}


@pytest.mark.parametrize("case", list(BOARD_CASES))
def test_bad_board_fails_with_one_line(clean, tmp_path, case):
    w = workspace(clean, tmp_path)
    text, detail = BOARD_CASES[case]
    board = tmp_path / "board.yaml"
    board.write_text(text)
    line = fail_case(case, case, w, board, "--board", board)
    assert detail in line  # rich markup would eat "[[x,y,z]"


def test_missing_board_file(clean, tmp_path):
    w = workspace(clean, tmp_path)
    fail_case("board file missing", "board file missing", w, tmp_path / "nope.yaml",
              "--board", tmp_path / "nope.yaml")


# ----------------------------------------------------------------------------- options / out
def test_out_under_a_regular_file(clean, tmp_path):
    """We run as root, so chmod 000 would not bite: a path below a regular file cannot be
    created by anyone."""
    w = workspace(clean, tmp_path)
    blocker = tmp_path / "some_file"
    blocker.write_text("not a folder")
    code, text = cli("calibrate", w.ds, "--out", blocker / "x", "--refine", "none")
    assert_one_line_failure(w, code, text, blocker, (
        "--out below a regular file", "--out below a regular file",
        "calibrate <dataset> --out <tmp>/some_file/x"))
    code, text = cli("calibrate", w.ds, "--out", blocker, "--refine", "none")
    assert_one_line_failure(w, code, text, blocker, (
        "--out is a regular file", "--out is a regular file",
        "calibrate <dataset> --out <tmp>/some_file"))
    assert blocker.read_text() == "not a folder"


@pytest.mark.parametrize("case, text, names", [
    ("--fix file relative to another reference",
     "reference: cam8\ncameras:\n  cam8: {T_ref_cam: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}\n"
     "  cam7: {T_ref_cam: [[1,0,0,0.4],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}\n", "fix.yaml"),
    ("--fix file with a sigma that is not a number",
     "cameras:\n  cam7: {T_ref_cam: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "
     "sigma_rotation_deg: abc}\n", "sigma_rotation_deg"),
    ("--fix file whose translation_m disagrees with T_ref_cam",
     "cameras:\n  cam7: {T_ref_cam: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}\n"
     "  cam8: {T_ref_cam: [[1,0,0,0.4],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "
     "translation_m: [0.5, 0, 0]}\n", "translation_m"),
    ("--fix file with a non-rigid T_ref_cam",
     "cameras:\n  cam7: {T_ref_cam: [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}\n", "rigid"),
])
def test_bad_fix_file(clean, tmp_path, case, text, names):
    w = workspace(clean, tmp_path)
    fix = tmp_path / "fix.yaml"
    fix.write_text(text)
    line = fail_case(case, case, w, fix, "--fix", fix)
    assert names in line


@pytest.mark.parametrize("case, text", [
    ("--config with an unknown key", "pose:\n  min_marker: 3\n"),
    ("--config with a value out of range", "pose:\n  min_markers: 0\n"),
])
def test_bad_config_file(clean, tmp_path, case, text):
    w = workspace(clean, tmp_path)
    cfg = tmp_path / "calib.yaml"
    cfg.write_text(text)
    fail_case(case, case, w, cfg, "--config", cfg)


def test_other_commands_fail_with_one_line(clean, tmp_path):
    w = workspace(clean, tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    line = fail_case("report on a folder without a calibration",
                     "report on a folder without a calibration", w, empty / "report.json",
                     empty, command="report")
    assert "missing" in line
    init = tmp_path / "init.yaml"
    init.write_text("cameras: {cam7: {T_ref_cam: [[1, 0], [0, 1]]}}\n")
    fail_case("refine --init with a 2x2 matrix", "refine --init with a 2x2 matrix", w, init,
              w.ds, "--init", init, "--out", tmp_path / "r", command="refine")
    nodes = tmp_path / "Nodes.csv"
    nodes.write_text("garbage\n1 2\n")
    fail_case("posegraph on a garbage CSV", "posegraph on a garbage CSV", w, nodes, nodes,
              nodes, "--out", tmp_path / "pg", command="posegraph")


# ----------------------------------------------------------------------------- no valid result
def test_no_detections_anywhere(clean, tmp_path):
    w = workspace(clean, tmp_path)
    for p in w.ds.glob("*/color/*.png"):
        rewrite(p, lambda img: np.full_like(img, 128))
    line = fail_case("no board marker in any image", "no board marker in any image", w, w.ds)
    assert "0 board markers detected" in line


def test_markers_not_on_the_board(clean, tmp_path):
    """The images show ids 0-55; this board file has ids 60-87 (same dictionary)."""
    w = workspace(clean, tmp_path)
    board = tmp_path / "board.yaml"
    board.write_text(G + "grid: {rows: 4, cols: 7, marker_length: 0.04, separation: 0.02, "
                     "front_first_id: 60}\n")
    line = fail_case("markers in the images are not on --board",
                     "markers in the images are not on --board", w, w.ds, "--board", board)
    assert "no usable board view" in line


def test_reference_never_sees_the_board(clean, tmp_path):
    """rig.yaml's reference (cam7) shows no board: the others are calibrated in the frame of
    the camera with the most shared views, and cam7 is named not calibrated with the reason
    and the fix (POOR, exit 3) instead of no result at all."""
    w = workspace(clean, tmp_path)
    for p in (w.ds / "cam7" / "color").glob("*.png"):
        rewrite(p, lambda img: np.full_like(img, 90))
    code, text = calibrate(w)
    assert code == 3, text
    data = yaml.safe_load((w.out / "extrinsics.yaml").read_text())
    ref = data["reference"]
    assert ref != "cam7" and set(data["cameras"]) == {"cam8", "cam9", "cam10"}
    gt = load_ground_truth(w.ds)
    for name, cam in data["cameras"].items():
        truth = np.linalg.inv(gt.T_ref_cam[ref]) @ gt.T_ref_cam[name]
        deg, mm = transform_error(np.asarray(cam["T_ref_cam"]), truth)
        assert mm < E2E_MM and deg < E2E_DEG, (name, mm, deg)
    report = json.loads((w.out / "report.json").read_text())
    why = report["unconnected"]["cam7"]
    assert "no usable board view" in why and f"reference frame is {ref!r}" in why, why
    assert "rig.yaml" in why and report["summary"]["verdict"] == "poor"
    ok_case("the reference camera never sees the board",
            "the reference camera never sees the board", w, text,
            f"`unconnected.cam7`, `reference: {ref}`, warning `not_calibrated`, verdict POOR",
            code=3)


def test_no_camera_shares_a_view(clean, tmp_path):
    """The dataset-level line of pipelines/calibrate.py, not the pose graph's own error (which
    names no dataset: 'no board view is seen by two connected cameras ...')."""
    w = workspace(clean, tmp_path)
    for k, cam in enumerate(("cam8", "cam9", "cam10")):
        rename_frames(w.ds, w.out, cam, str(7 + k))
    line = fail_case("no camera shares a board view with the reference",
                     "no camera shares a board view with the reference", w, w.ds)
    assert "shares a board view with the reference 'cam7'" in line
    assert "move the board where two cameras see it at once" in line


# ----------------------------------------------------------------------------- valid results
def test_camera_that_never_shares_a_view(clean, tmp_path):
    w = workspace(clean, tmp_path)
    rename_frames(w.ds, w.out, "cam10", "9")
    code, text = calibrate(w)
    assert code == 3, text  # a valid result for the others, but POOR: not a success
    report = check_result(w, ["cam7", "cam8", "cam9"], expect_missing=("cam10",))
    assert "cam10" in report["unconnected"] and report["summary"]["verdict"] == "poor"
    assert any(x["code"] == "not_calibrated" and x["cameras"] == ["cam10"]
               for x in report["warnings"])
    ok_case("camera never shares a view", "a camera that never shares a view (cam10)", w, text,
            "`unconnected.cam10`, warning `not_calibrated`, verdict POOR", code=3)


def test_wrong_intrinsics_on_one_camera(clean, tmp_path):
    """cam9 gets another camera's intrinsics file: fx scaled by 1.05. Every view of cam9
    disagrees with the rig the same way: a model error, not outlier views (issue 13, item 4).
    It used to be dropped as all-outlier; now the pose graph flags it (warning
    ``camera_model_error`` naming it and the likely causes) and the default ``auto``
    self-calibration frees the intrinsics: cam9 is kept, its fx recovered, its error within
    3 sigma. (With ``bundle.intrinsics: fixed`` it is kept with its sigma inflated instead:
    tests/test_intrinsics.py.)"""
    w = workspace(clean, tmp_path)
    edit_rig(w.ds, lambda r: r["cameras"]["cam9"].update(fx=r["cameras"]["cam9"]["fx"] * 1.05))
    code, text = calibrate(w)
    assert code == 0, text
    report = check_result(w, ["cam7", "cam8", "cam10"])
    assert report["cameras"]["cam9"]["calibrated"] and "cam9" not in report["unconnected"]
    found = [x for x in report["warnings"] if x["code"] == "camera_model_error"]
    assert any(x["cameras"] == ["cam9"] and "intrinsics" in x["advice"] for x in found)
    flagged = {m["camera"]: m for m in report["pose_graph"]["model_error"]}
    assert "cam9" in flagged
    assert "fx" in report["bundle"]["self_calibration"]["intrinsics_params"]
    fx = report["cameras"]["cam9"]["intrinsics_refined"]["fx"]
    assert abs(fx["refined"] * 1.05 / fx["prior"] - 1.0) < 0.002, fx  # back to the truth
    gt = load_ground_truth(w.ds)
    cam9 = report["cameras"]["cam9"]
    deg, mm = transform_error(np.asarray(cam9["T_ref_cam"]), gt.T_ref_cam["cam9"])
    assert mm < 3.0 * cam9["sigma_translation_mm"], (mm, cam9["sigma_translation_mm"])
    assert deg < 3.0 * cam9["sigma_rotation_deg"], (deg, cam9["sigma_rotation_deg"])
    ok_case("wrong intrinsics", "wrong intrinsics on one camera (cam9 fx x 1.05)", w, text,
            "`pose_graph.model_error` (cam9, kept), warning `camera_model_error`, "
            "`bundle.self_calibration` (intrinsics refined, fx recovered)")


STRAY_PX = 40  # a poster-sized stray: small copies (< ~17 px here) are not even detected
STRAY_AT = 60  # px from the top-left corner (a marker pasted at 10 px is not detected)


def _stray_markers(w: Work) -> list[tuple[str, str, int]]:
    """Frame 2, every camera: a copy of a board marker its view shows, pasted in the top-left
    corner, away from the board (the same id twice in one image). Frame 4: the board's own
    copy of a marker is painted over and the marker pasted in the corner instead (a single
    copy at the wrong place: only the pose stage can tell it is off the board)."""
    det = cached_detections(w.out)
    views = []
    for cam in ("cam7", "cam8", "cam9", "cam10"):
        for frame, cover in (("000002", False), ("000004", True)):
            d = det.get((cam, frame))
            if not d or len(d["ids"]) < 6:
                continue
            corners = np.asarray(d["corners_px"], float)
            clear = STRAY_AT + 2 * STRAY_PX
            assert corners[..., 0].min() > clear or corners[..., 1].min() > clear
            mid = int(d["ids"][len(d["ids"]) // 2])

            def edit(img, quad=corners[d["ids"].index(mid)], mid=mid, cover=cover):
                if cover:  # paint the board's copy over (it reads as a marker-less patch)
                    cv2.fillConvexPoly(img, np.round(quad).astype(np.int32), (230, 230, 230))
                return paste(img, marker_image(mid, STRAY_PX), STRAY_AT, STRAY_AT)

            rewrite(w.ds / cam / "color" / f"{frame}.png", edit)
            views.append((cam, frame, mid))
    return views


def _strays_detected(w: Work, views) -> int:
    """How many pasted strays the detector reported: as a duplicate id (both copies then
    dropped), or as the only copy of their id, at the paste position."""
    det = cached_detections(w.out)
    found = 0
    for cam, frame, mid in views:
        d = det[(cam, frame)]
        at = {int(i): np.mean(c, axis=0) for i, c in zip(d["ids"], d["corners_px"])}
        found += mid in d["duplicate_ids"] or (mid in at and at[mid].max() < 2 * STRAY_AT)
    return found


@pytest.fixture(scope="module")
def stray_run(clean, tmp_path_factory):
    w = workspace(clean, tmp_path_factory.mktemp("stray"))
    views = _stray_markers(w)
    code, text = calibrate(w)
    return w, views, code, text


def test_stray_board_marker_away_from_the_board(stray_run):
    w, views, code, text = stray_run
    assert len(views) >= 6
    assert code == 0, text
    assert _strays_detected(w, views) >= len(views) // 2  # the corruption reached the pipeline
    check_result(w, ["cam7", "cam8", "cam9", "cam10"])
    report = json.loads((w.out / "report.json").read_text())
    dropped = sorted({r["reason"] for r in report["dropped_views"]})
    ok_case("stray marker", "a stray copy of a board marker away from the board "
            f"({len(views)} views)", w, text, f"dropped_views {dropped or 'none'}; the strays "
            "themselves not listed (xfail)")


@pytest.mark.xfail(strict=True, reason="report.json does not say that markers were dropped as "
                   "strays (duplicate ids at detection, pose-stage outliers): "
                   "see docs/robustness.md, 'Known gaps'")
def test_stray_markers_are_listed_in_the_report(stray_run):
    w, views, code, text = stray_run
    assert code == 0, text
    report = json.loads((w.out / "report.json").read_text())
    text = json.dumps(report)
    listed = {(v["camera"], v["frame"]) for v in report["dropped_views"]}
    for cam, frame, _ in views:
        assert (cam, frame) in listed or f'"{cam}/{frame}"' in text or any(
            v["camera"] == cam and v["frame"] == frame and v.get("dropped_markers")
            for v in report["views"]), (cam, frame)


def test_a_stray_copy_costs_only_its_own_id(clean):
    """Duplicated ids are dropped before refineDetectedMarkers (was: the duplicate spoiled its
    board fit and one stray cost about half the view's markers, 21 -> 13)."""
    from rgbd_calib.detect.markers import detect_markers

    board = thesis_board()
    img = cv2.imread(str(clean.dataset / "cam9" / "color" / "000002.png"))
    before = detect_markers(img, board)
    assert len(before.ids) > 12
    mid = int(before.ids[0])
    after = detect_markers(paste(img.copy(), marker_image(mid, STRAY_PX), STRAY_AT, STRAY_AT),
                           board)
    assert mid in after.duplicate_ids
    missing = set(before.ids.tolist()) - {mid} - set(after.ids.tolist())
    assert not missing, f"{len(missing)} other markers lost: {sorted(missing)}"


BLUR_FRAMES = ("000002", "000004")


def _blur(w: Work, length_px: int) -> None:
    """Horizontal motion blur (a line kernel) on two of the six frames, every camera."""
    kernel = np.zeros((length_px, length_px), np.float32)
    kernel[length_px // 2, :] = 1.0 / length_px
    for frame in BLUR_FRAMES:
        for p in w.ds.glob(f"*/color/{frame}.png"):
            rewrite(p, lambda img: cv2.filter2D(img, -1, kernel))


@pytest.fixture(scope="module", params=[5, 15], ids=["5px", "15px"])
def blur_run(clean, tmp_path_factory, request):
    w = workspace(clean, tmp_path_factory.mktemp(f"blur{request.param}"))
    _blur(w, request.param)
    code, text = calibrate(w)
    return request.param, w, code, text


def test_motion_blurred_frames(blur_run):
    """5 px: the markers are still found but their corners are worse; 15 px: not found."""
    length_px, w, code, text = blur_run
    assert code == 0, text
    report = check_result(w, ["cam7", "cam8", "cam9", "cam10"])
    used = {(v["camera"], v["frame"]) for v in report["views"]}
    if length_px == 15:
        assert not any(f in BLUR_FRAMES for _, f in used)
    dropped = sorted({r["reason"] for r in report["dropped_views"]})
    ok_case(f"blur {length_px}", f"motion blur, {length_px} px line kernel, 2 of 6 frames",
            w, text, f"dropped_views {dropped or 'none'}; "
            + ("blurred frames absent from `views`" if length_px == 15
               else "degraded views used, not flagged (xfail)"))


@pytest.mark.xfail(strict=True, reason="a motion-blurred view whose markers are still found is "
                   "used and not flagged (corners biased, error 15-30x the clean one): see "
                   "docs/robustness.md, 'Known gaps'")
def test_motion_blurred_views_are_flagged(blur_run):
    length_px, w, code, text = blur_run
    if length_px != 5:
        pytest.xfail("only the 5 px case has blurred views that are found")
    assert code == 0, text
    report = json.loads((w.out / "report.json").read_text())
    flagged = {(v["camera"], v["frame"]) for v in report["dropped_views"]}
    for v in report["views"]:
        if v["frame"] in BLUR_FRAMES:
            assert (v["camera"], v["frame"]) in flagged or v.get("blur_px"), v


def test_foreign_markers_are_ignored(clean, tmp_path):
    """Markers of the board's dictionary that are not on the board (ids 77, 88)."""
    w = workspace(clean, tmp_path)
    for p in sorted(w.ds.glob("*/color/00000[13].png")):
        rewrite(p, lambda img: paste(paste(img, marker_image(77, 40), 10, 10),
                                     marker_image(88, 40), 1200, 640))
    code, text = calibrate(w)
    assert code == 0, text
    check_result(w, ["cam7", "cam8", "cam9", "cam10"])
    ok_case("foreign markers", "markers not on the board in 8 images (ids 77, 88)", w, text,
            "nothing to report (ids not on the board are ignored)")


# ----------------------------------------------------------------------------- Ctrl-C
def _descendants(pid: int) -> list[int]:
    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(x) for x in (task / "children").read_text().split()]
            except OSError:
                continue
            found += kids
            todo += kids
    return found


def _wait(condition, timeout_s: float = 90.0) -> None:
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout_s, "timed out"
        time.sleep(0.02)


def _sigint_ignored() -> bool:
    """Whether this process ignores SIGINT at the OS level (/proc SigIgn mask)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))
    return False


def _interrupted_line(run: subprocess.CompletedProcess) -> str:
    """The one line an interrupted command prints (exit 130, nothing on stdout)."""
    assert run.returncode == 130, run.stderr
    assert run.stdout == ""
    lines = [ln for ln in run.stderr.strip().splitlines() if not PROGRESS_LINE.match(ln)]
    assert len(lines) == 1 and lines[0].startswith("interrupted"), run.stderr
    return lines[0]


def _cache_count(out: Path) -> int:
    try:
        return len(json.loads((out / "cache" / "detections.json").read_text())["images"])
    except (OSError, ValueError, KeyError):
        return -1


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_ctrl_c_leaves_earlier_results_and_resumes(clean, tmp_path):
    """SIGINT to the whole process group, as Ctrl-C in a terminal sends it: once while the
    detection pool works, once after detection (the cache is complete) while the pipeline
    goes on; then the same command again finishes from the detection cache."""
    w = workspace(clean, tmp_path, cache=False)
    # eight copies of every frame set (new frame names), so that detection lasts long enough
    # (seconds) for the first interrupt to land while the pool works
    for png in sorted(w.ds.glob("*/*/*.png")):
        for k in range(1, 8):
            shutil.copy2(png, png.with_name(f"{int(png.stem) + 1000 * k:06d}.png"))
    n_images = sum(1 for _ in w.ds.glob("*/color/*.png"))
    args = [RGBD_CALIB, "calibrate", w.ds, "--out", w.out, "--refine", "none", "--workers", "2"]

    def interrupted_run(when) -> subprocess.CompletedProcess:
        # SIGINT at its default in the child, as in a terminal: a native library loaded by an
        # earlier test in this process can leave it ignored at the OS level, and a Python
        # started with SIGINT ignored never raises KeyboardInterrupt
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            _wait(lambda: when(proc.pid))
            os.killpg(proc.pid, signal.SIGINT)
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        return subprocess.CompletedProcess(args, proc.returncode, out, err)

    # 1. during detection: the pool's workers exist (children of the forkserver)
    def pool_working(pid: int) -> bool:
        if len(_descendants(pid)) >= 4:  # forkserver, resource tracker, 2 workers
            time.sleep(0.3)
            return True
        return False

    ignored = _sigint_ignored()
    run1 = interrupted_run(pool_working)
    assert _cache_count(w.out) < n_images, (
        f"the interrupt did not stop detection (exit {run1.returncode}; SIGINT ignored in "
        f"pytest: {ignored})"
    )
    line1 = _interrupted_line(run1)
    assert line1.startswith("interrupted: earlier results were left untouched"), run1.stderr
    assert (w.out / "extrinsics.yaml").read_bytes() == w.earlier
    assert (w.out / "report.json").read_bytes() == w.earlier_report
    assert not [p for p in w.out.iterdir() if p.name.startswith(".")]
    record("Ctrl-C", "Ctrl-C (SIGINT to the process group) during detection, and after it",
           "calibrate <dataset>", 130, line1)
    # 2. after detection (the cache holds every image) while the pipeline goes on. When the
    #    signal lands is up to the machine (the pose graph takes ~1 s, a loaded CI machine can
    #    be slower to send it): before the renames the earlier result stays, during or after
    #    them the new one is complete; either way the folder is one run's, never a mix, and
    #    the line says which
    run2 = interrupted_run(lambda pid: _cache_count(w.out) == n_images)
    line2 = _interrupted_line(run2)
    assert not [p for p in w.out.iterdir() if p.name.startswith(".")]
    if line2.startswith("interrupted: earlier results were left untouched"):
        assert (w.out / "extrinsics.yaml").read_bytes() == w.earlier
        assert (w.out / "report.json").read_bytes() == w.earlier_report
    else:
        assert line2 == (f"interrupted after the results were written: {w.out} complete; "
                         "nothing to run again"), run2.stderr
        assert (w.out / "extrinsics.yaml").read_bytes() != w.earlier
        assert (w.out / "report.json").read_bytes() != w.earlier_report
        check_result(w, ["cam7", "cam8", "cam9", "cam10"])

    code, text = calibrate(w, "--workers", "2")
    assert code == 0, text
    timings = json.loads((w.out / "report.json").read_text())["timings_s"]
    # the resume reads the cache: per image at least 10x faster than the clean detection
    # (the clean set has 1/8 of these images)
    n_clean = sum(1 for _ in clean.dataset.glob("*/color/*.png"))
    per_image = timings["detection"] / n_images
    assert per_image < 0.1 * clean.detection_s / n_clean, (timings, clean.detection_s)
    check_result(w, ["cam7", "cam8", "cam9", "cam10"])


def test_interrupted_detection_keeps_what_it_detected(clean, tmp_path):
    """Library level: an interrupt after k images saves those k; the next run starts there."""
    from rgbd_calib.core.config import DetectionConfig
    from rgbd_calib.detect.run import detect_dataset
    from rgbd_calib.model.dataset import FolderDataset

    ds = FolderDataset(clean.dataset)
    cache = tmp_path / "detections.json"
    k = 3

    def stop_after(n):
        calls = []

        def progress(count):
            calls.append(count)
            if len(calls) > n:
                raise KeyboardInterrupt

        return progress, calls

    progress, calls = stop_after(k)
    with pytest.raises(KeyboardInterrupt):
        detect_dataset(ds, thesis_board(), DetectionConfig(), cache, workers=1, progress=progress)
    assert calls[0] == 0
    assert len(json.loads(cache.read_text())["images"]) == k
    progress, calls = stop_after(1)
    with pytest.raises(KeyboardInterrupt):
        detect_dataset(ds, thesis_board(), DetectionConfig(), cache, workers=1, progress=progress)
    assert calls[0] == k  # resumed: k images came from the cache
    assert len(json.loads(cache.read_text())["images"]) == k + 1


# ----------------------------------------------------------------------------- depth stage
def test_camera_without_depth_on_the_board_does_not_abort(clean, tmp_path):
    """A depth stream of zeros: no depth-scale estimate for that camera, no abort (was a
    DatasetError out of the whole calibration before c8f0708)."""
    from rgbd_calib.core.geometry import invert_transform
    from rgbd_calib.depth.stage import measure_depth
    from rgbd_calib.model.dataset import FolderDataset

    w = workspace(clean, tmp_path, cache=False)
    for p in (w.ds / "cam8" / "depth").glob("*.png"):  # the depth stream delivered zeros
        rewrite(p, np.zeros_like)
    ds = FolderDataset(w.ds)
    gt = load_ground_truth(w.ds)
    T_ref_cam = {"cam8": gt.T_ref_cam["cam8"]}
    views = {"cam8": {f: invert_transform(T_ref_cam["cam8"]) @ T
                      for f, T in gt.T_ref_board.items()}}
    depth = measure_depth(ds, thesis_board(), T_ref_cam, views, gt.T_ref_board, "none")
    assert "cam8" not in depth.depth_scales


# ----------------------------------------------------------------------------- 5 % corrupted
@pytest.fixture(scope="module")
def race40(tmp_path_factory):
    from rgbd_calib.synth.render import SynthParams, synthesize

    out = tmp_path_factory.mktemp("race40") / "race"
    return synthesize(out, "race", 40, 11, thesis_board(), SynthParams(), workers=2)


def _swap_markers(img: np.ndarray, quad_a: np.ndarray, quad_b: np.ndarray) -> np.ndarray:
    """Swap the image content of two markers (perspective warp of each onto the other)."""
    out = img.copy()
    h, w = img.shape[:2]
    for src, dst in ((quad_a, quad_b), (quad_b, quad_a)):
        H = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
        warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR)
        mask = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(mask, np.round(dst).astype(np.int32), 255)
        out[mask > 0] = warped[mask > 0]
    return out


def _corrupt_views(ds: Path, detections: dict, fraction: float, seed: int) -> list[tuple]:
    """Corrupt ``fraction`` of the board views: half get two marker ids swapped, half a stray
    copy of a board marker pasted away from the board (an id its view does not show, when the
    face has one, so only the pose stage can reject it)."""
    board = thesis_board()
    views = sorted(k for k, d in detections.items() if len(d["ids"]) >= 4)
    rng = np.random.default_rng(seed)
    n = math.ceil(fraction * len(views))
    done = []
    for idx in rng.permutation(len(views)):
        if len(done) == n:
            break
        cam, frame = views[idx]
        d = detections[(cam, frame)]
        ids = list(d["ids"])
        corners = np.asarray(d["corners_px"], float)
        path = ds / cam / "color" / f"{frame}.png"
        img = cv2.imread(str(path))
        if len(done) % 2 == 0:
            a, b = rng.choice(len(ids), 2, replace=False)
            img = _swap_markers(img, corners[a], corners[b])
            kind = f"swap {ids[a]}<->{ids[b]}"
        else:
            face = board.faces[board.index_of[ids[0]]]
            unseen = [int(i) for i in board.face_ids(face) if int(i) not in ids]
            mid = int(rng.choice(unseen)) if unseen else int(ids[0])
            side = max(int(np.median(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=-1))),
                       32)  # smaller pasted copies are not detected at 848x480
            patch = marker_image(mid, side)
            lo, hi = corners.reshape(-1, 2).min(0), corners.reshape(-1, 2).max(0)
            h, w = img.shape[:2]
            ph, pw = patch.shape[:2]
            spots = [(x, y) for x in (20, w - pw - 20) for y in (20, h - ph - 20)]
            free = [(x, y) for x, y in spots
                    if x + patch.shape[1] < lo[0] - 10 or x > hi[0] + 10
                    or y + patch.shape[0] < lo[1] - 10 or y > hi[1] + 10]
            if not free:
                continue
            x, y = max(free, key=lambda s: np.hypot(*(np.array(s) - (lo + hi) / 2)))
            img = paste(img, patch, x, y)
            kind = f"stray {mid}"
        assert cv2.imwrite(str(path), img)
        done.append((cam, frame, kind))
    assert len(done) == n
    return done


@pytest.mark.slow
def test_five_percent_corrupted_views_on_the_race_rig(race40, tmp_path):
    """With 5 % of the board views corrupted (swapped ids, stray markers carrying board ids),
    every camera's error stays within 10 % of the clean result, or within 0.1 mm / 0.005 deg
    of it when that is larger (a 10 % band of a ~0.05 mm error is below the noise of one
    re-detected view)."""
    clean_out = tmp_path / "clean"
    code, text = cli("calibrate", race40.path, "--out", clean_out, "--refine", "none")
    assert code == 0, text
    ds = tmp_path / "ds"
    shutil.copytree(race40.path, ds)
    out = tmp_path / "corrupt"
    (out / "cache").mkdir(parents=True)
    shutil.copy2(clean_out / "cache" / "detections.json", out / "cache")
    clean_det = cached_detections(out)
    corrupted = _corrupt_views(ds, clean_det, 0.05, seed=5)
    code, text = cli("calibrate", ds, "--out", out, "--refine", "none")
    assert code == 0, text
    # the corruption reached the pipeline: ids at the wrong place, or duplicates
    det = cached_detections(out)
    effective = 0
    for cam, frame, _ in corrupted:
        a, b = clean_det[(cam, frame)], det[(cam, frame)]
        at = {int(i): np.mean(c, axis=0) for i, c in zip(a["ids"], a["corners_px"])}
        moved = [i for i, c in zip(b["ids"], b["corners_px"])
                 if i not in at or np.linalg.norm(np.mean(c, axis=0) - at[i]) > 3.0]
        effective += bool(moved or b["duplicate_ids"])
    assert effective >= len(corrupted) // 2, (effective, corrupted)

    gt = load_ground_truth(race40.path)
    before = yaml.safe_load((clean_out / "extrinsics.yaml").read_text())["cameras"]
    after = yaml.safe_load((out / "extrinsics.yaml").read_text())["cameras"]
    assert set(after) == set(before)
    rows = []
    for name in before:
        deg0, mm0 = transform_error(np.asarray(before[name]["T_ref_cam"]), gt.T_ref_cam[name])
        deg1, mm1 = transform_error(np.asarray(after[name]["T_ref_cam"]), gt.T_ref_cam[name])
        rows.append((name, mm0, mm1, deg0, deg1))
        assert mm1 <= mm0 + max(0.1 * mm0, 0.1), rows
        assert deg1 <= deg0 + max(0.1 * deg0, 0.005), rows
    print("\ncamera, error clean -> corrupted (mm, deg):")
    for name, mm0, mm1, deg0, deg1 in rows:
        print(f"  {name}: {mm0:.3f} -> {mm1:.3f} mm, {deg0:.4f} -> {deg1:.4f} deg")
    n_views = sum(len(d["ids"]) >= 4 for d in clean_det.values())
    record("5% corrupted", f"{len(corrupted)} of the race rig's {n_views} board views (5 %) "
           "corrupted: swapped ids, stray markers with board ids",
           "calibrate <dataset>", code,
           "summary table; every camera within 10 % (or 0.1 mm / 0.005 deg) of the clean error")


# ----------------------------------------------------------------------------- the doc table
def table() -> str:
    lines = ["| Bad input | Command | Exit | What the user sees |", "|---|---|---|---|"]
    for what, command, code, seen in ROWS.values():
        # a result (0, or 3: written but POOR) is described; an error line is quoted
        cells = [what, f"`{command}`", code, seen if code in ("0", "3") else f"`{seen}`"]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines)


@pytest.mark.parametrize("side_px, expected", [
    (12.0, "12 px wide (median), at ArUco's limit: bring the board closer"),
    (60.0, "): corners do not fit a pose: motion blur"),
])
def test_no_usable_view_says_why_the_views_with_markers_were_dropped(side_px, expected):
    """Measured: an A3 ChArUco board (configs/board_charuco_a3.yaml) on the race rig (848x480,
    seed 104), calibrated with the thesis board file by mistake, gives 577 markers of 12 px
    in 53 views and not one pose. The error gives the drop reasons, the markers' size when it
    is at ArUco's limit, and the board-file check."""
    from rgbd_calib.detect.markers import MarkerDetections
    from rgbd_calib.pipelines.calibrate import _why_dropped
    from rgbd_calib.solve.pose import RejectedView

    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float) * side_px + 100
    det = MarkerDetections(np.array([3, 4]), np.stack([square, square + 2 * side_px]),
                           np.ones((2, 4), bool))
    rejected = [RejectedView("cam0", "000001", "reprojection_rms", 2),
                RejectedView("cam1", "000001", "reprojection_rms", 2),
                RejectedView("cam1", "000002", "ambiguous", 2)]
    detections = {("cam0", "000001"): det, ("cam1", "000001"): det, ("cam1", "000002"): det}
    why = _why_dropped(detections, rejected)
    assert why.startswith("all 3 views with markers were dropped (reprojection_rms 2, "
                          "ambiguous 1)"), why
    assert expected in why, why
    # the same failure comes from a board file of another layout whose ids are printed here
    assert "check that --board matches the printed board" in why, why



def test_zz_every_case_is_in_docs_robustness(tmp_path_factory):
    """Runs last in this module: the rows of the cases that ran are in docs/robustness.md
    verbatim (``RGBD_CALIB_WRITE_DOCS=1`` rewrites the table from this run: run it with the
    slow tier too, ``RGBD_CALIB_SLOW=1``, or the slow cases' rows are lost)."""
    if not ROWS:
        pytest.skip("no case ran")
    text = table()
    (tmp_path_factory.getbasetemp() / "robustness_table.md").write_text(text + "\n")
    doc = DOC.read_text()
    if os.environ.get("RGBD_CALIB_WRITE_DOCS") == "1":
        head, rest = doc.split(TABLE_START)
        _, tail = rest.split(TABLE_END)
        DOC.write_text(f"{head}{TABLE_START}\n{text}\n{TABLE_END}{tail}")
        return
    missing = [row for row in text.splitlines()[2:] if row not in doc]
    assert not missing, "rows not in docs/robustness.md (RGBD_CALIB_WRITE_DOCS=1 updates):\n" + (
        "\n".join(missing))



def test_image_header_reads_the_ends_of_a_png_and_finds_a_jpeg_frame_behind_metadata(tmp_path):
    """The pre-flight header check reads a PNG's first 64 and last 12 bytes only, and still
    finds a JPEG's frame header behind a large metadata segment (here 20 kB of APP1)."""
    from rgbd_calib.core.errors import DatasetError
    from rgbd_calib.model.dataset import image_header

    image = np.zeros((48, 64, 3), np.uint8)
    png = tmp_path / "a.png"
    png.write_bytes(cv2.imencode(".png", image)[1].tobytes())
    assert (image_header(png).width, image_header(png).height) == (64, 48)
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    app1 = b"\xff\xe1" + struct.pack(">H", 20002) + bytes(20000)
    (jpg := tmp_path / "a.jpg").write_bytes(jpeg[:2] + app1 + jpeg[2:])
    header = image_header(jpg)
    assert (header.kind, header.width, header.height) == ("jpeg", 64, 48)
    png.write_bytes(png.read_bytes()[:-5])  # truncated: no IEND trailer
    with pytest.raises(DatasetError, match="truncated PNG"):
        image_header(png)
