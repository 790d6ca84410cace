"""The recorded RGB-D set in folder form (docs/formats.md): read lazily, written in one way.

Only file names are indexed up front; images are decoded one at a time when asked for, so
a set of any size streams through in constant memory. Every read checks what the contract
promises (colour size = intrinsics, depth 16-bit single-channel of the same size) and fails
with one line naming the file.

:class:`FolderWriter` is the one writer of the form, for ``convert``, ``record`` and ``synth``:
inside :func:`staged_folder` (a sibling renamed into place at the end) or set by set, each set
renamed into place whole.
"""

from __future__ import annotations

import copy
import os
import shutil
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path

import cv2
import imagecodecs
import numpy as np

from ..core.errors import DatasetError
from ..core.interrupts import mark_committed, sigint_deferred
from ..core.progress import Tick
from .rig import CAMERA_NAME, Rig, load_rig, save_rig

COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
TIMESTAMPS_FILE = "timestamps.csv"  # <dataset>/<camera>/timestamps.csv, optional
TIMESTAMPS_HEADER = "frame,t_ms"


@dataclass(frozen=True)
class FrameSet:
    """One synchronised capture: the files each camera has for frame ``frame``."""

    frame: str
    color: dict[str, Path]
    depth: dict[str, Path]


@dataclass(frozen=True)
class DatasetSummary:
    cameras: list[str]
    n_frames: int
    frames_per_camera: dict[str, int]
    missing: dict[str, list[str]]  # camera -> frames other cameras have but this one lacks
    depth_cameras: list[str]

    def to_dict(self) -> dict:
        return {
            "cameras": self.cameras,
            "n_frames": self.n_frames,
            "frames_per_camera": self.frames_per_camera,
            "missing": {c: len(m) for c, m in self.missing.items()},
            "depth_cameras": self.depth_cameras,
        }


class FolderDataset:
    """Index of ``<dataset>/<camera>/{color,depth}/<frame>.png`` with its ``rig.yaml``."""

    def __init__(self, path: Path, rig: Rig | None = None):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise DatasetError(f"{self.path}: is a file, not a dataset folder; check the path")
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: dataset folder not found; check the path")
        rig_path = self.path / "rig.yaml"
        if rig is None:
            if not rig_path.is_file():
                raise DatasetError(
                    f"{rig_path}: missing; add a rig.yaml with the cameras' intrinsics "
                    "(docs/formats.md)"
                )
            rig = load_rig(rig_path)
        self.rig = rig
        folders = sorted(
            p.name for p in self.path.iterdir() if p.is_dir() and (p / "color").is_dir()
        )
        extra = [f for f in folders if f not in rig.cameras]
        if extra:
            raise DatasetError(
                f"{self.path}: camera folder(s) {', '.join(extra)} have no entry "
                f"in {rig_path.name}; add their intrinsics or remove the folders"
            )
        absent = [c for c in rig.cameras if c not in folders]
        if absent:
            raise DatasetError(
                f"{self.path}: camera(s) {', '.join(absent)} of "
                f"{rig_path.name} have no <camera>/color folder; record them or "
                "remove them from the rig"
            )
        self._color: dict[str, dict[str, Path]] = {}
        self._depth: dict[str, dict[str, Path]] = {}
        for cam in rig.cameras:
            if not CAMERA_NAME.match(cam):
                raise DatasetError(
                    f"{self.path / cam}: invalid camera folder name; use letters, digits, _ and -"
                )
            self._color[cam] = _index_images(self.path / cam / "color", COLOR_SUFFIXES)
            depth_dir = self.path / cam / "depth"
            self._depth[cam] = _index_images(depth_dir, (".png",)) if depth_dir.is_dir() else {}
        self.frames = sorted(set().union(*(set(c) for c in self._color.values())))
        if not self.frames:
            raise DatasetError(
                f"{self.path}: no colour images found under <camera>/color/; "
                "is this the dataset folder?"
            )
        self._times: dict[str, dict[str, float] | None] = {}  # read on first ask

    @property
    def cameras(self) -> list[str]:
        return self.rig.names

    def with_rig(self, rig: Rig) -> FolderDataset:
        """The same frames with another rig (e.g. refined intrinsics), without scanning the
        folder again; ``rig`` must name the same cameras."""
        out = copy.copy(self)
        out.rig = rig
        return out

    def has_depth(self, camera: str) -> bool:
        return bool(self._depth[camera])

    def summary(self) -> DatasetSummary:
        missing = {c: [f for f in self.frames if f not in self._color[c]] for c in self.cameras}
        return DatasetSummary(
            self.cameras,
            len(self.frames),
            {c: len(self._color[c]) for c in self.cameras},
            missing,
            [c for c in self.cameras if self.has_depth(c)],
        )

    def color_path(self, camera: str, frame: str) -> Path | None:
        return self._color[camera].get(frame)

    def depth_path(self, camera: str, frame: str) -> Path | None:
        return self._depth[camera].get(frame)

    def timestamps_ms(self, camera: str) -> dict[str, float] | None:
        """Capture time (ms, on the recording's clock) of each colour frame of ``camera`` from
        its optional ``<camera>/timestamps.csv`` (docs/formats.md), read on first use; None
        when the camera has no such file. Rows of frames the camera has no colour image of
        are left out (images may be deleted by hand); a frame without a row has no time.
        Raises :class:`DatasetError` naming the file and line of a malformed row."""
        if camera not in self._color:
            raise DatasetError(f"{self.path}: no camera {camera!r}; the cameras are "
                               f"{', '.join(self.cameras)}")
        if camera not in self._times:
            path = self.path / camera / TIMESTAMPS_FILE
            table = read_timestamps_csv(path) if path.is_file() else None
            self._times[camera] = None if table is None else {
                f: t for f, t in table.items() if f in self._color[camera]}
        times = self._times[camera]
        return None if times is None else dict(times)

    def frame_sets(self) -> Iterator[FrameSet]:
        """Synchronised frame sets in frame order (paths only; nothing is decoded)."""
        for f in self.frames:
            color = {c: self._color[c][f] for c in self.cameras if f in self._color[c]}
            depth = {c: self._depth[c][f] for c in self.cameras if f in self._depth[c]}
            yield FrameSet(f, color, depth)

    def check_images(self, progress: Tick | None = None) -> None:
        """Check every image's header against the contract before any long step runs.

        Reads a few bytes per file (PNG: the IHDR chunk and the IEND trailer; JPEG: up to the
        frame header): colour size = intrinsics, depth a 16-bit single-channel PNG of the same
        size, no truncated PNG. Raises DatasetError naming the first offending file. Damage
        inside the compressed data is only found when the image is decoded."""
        for cam in self.cameras:
            intr = self.rig.cameras[cam]
            for path in self._color[cam].values():
                info = image_header(path)
                _check_size(path, (info.width, info.height), intr.width, intr.height)
                if progress:
                    progress(1)
            for path in self._depth[cam].values():
                info = image_header(path)
                if info.kind != "png":
                    raise DatasetError(
                        f"{path}: depth must be a 16-bit single-channel PNG, got a "
                        f"{info.kind.upper()} file; export raw depth counts (z16) as PNG"
                    )
                if info.bit_depth != 16 or info.channels != 1:
                    raise DatasetError(
                        f"{path}: depth must be a 16-bit single-channel PNG, got "
                        f"{info.bit_depth}-bit, {info.channels} channel(s); export raw depth "
                        "counts (z16) aligned to colour"
                    )
                _check_size(path, (info.width, info.height), intr.width, intr.height, depth=True)
                if progress:
                    progress(1)

    def read_color(self, camera: str, frame: str, gray: bool = False) -> np.ndarray:
        path = self._color[camera].get(frame)
        if path is None:
            raise DatasetError(f"{self.path / camera / 'color'}: no frame {frame}")
        return read_color_image(
            path, self.rig.cameras[camera].width, self.rig.cameras[camera].height, gray
        )

    def read_depth(self, camera: str, frame: str) -> np.ndarray | None:
        path = self._depth[camera].get(frame)
        if path is None:
            return None
        intr = self.rig.cameras[camera]
        return read_depth_image(path, intr.width, intr.height)


def read_timestamps_csv(path: Path) -> dict[str, float]:
    """``frame -> t_ms`` of a ``timestamps.csv`` (header ``frame,t_ms``, one row per colour
    frame: its stem and capture time in milliseconds). Raises :class:`DatasetError` with the
    file, the line and the fix for a missing header, a row that is not ``stem,number``, a
    time that is not a finite number or a frame listed twice."""
    path = Path(path)
    fix = f"write one '<frame stem>,<time in ms>' row per colour frame under '{TIMESTAMPS_HEADER}'"
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable ({type(exc).__name__}); {fix}, or delete the "
                           "file (it is optional)") from None
    if not lines or lines[0].strip().replace(" ", "") != TIMESTAMPS_HEADER:
        raise DatasetError(f"{path}: line 1: the header must be '{TIMESTAMPS_HEADER}'; {fix}, "
                           "or delete the file (it is optional)")
    out: dict[str, float] = {}
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 2 or not fields[0]:
            raise DatasetError(f"{path}: line {n}: expected 'frame,t_ms', got {line.strip()!r}; "
                               f"{fix}")
        frame, value = fields
        try:
            t_ms = float(value)
        except ValueError:
            t_ms = float("nan")
        if not np.isfinite(t_ms):
            raise DatasetError(f"{path}: line {n}: time {value!r} of frame {frame!r} is not a "
                               f"finite number of milliseconds; {fix}")
        if frame in out:
            raise DatasetError(f"{path}: line {n}: frame {frame!r} is listed twice; keep one "
                               "row per frame")
        out[frame] = t_ms
    return out


def timestamps_csv_text(times_ms: dict[str, float]) -> str:
    """The ``timestamps.csv`` text of ``frame -> t_ms``, in frame order; times written with
    ``repr`` precision (they read back exactly)."""
    rows = [TIMESTAMPS_HEADER] + [f"{f},{float(times_ms[f])!r}" for f in sorted(times_ms)]
    return "\n".join(rows) + "\n"


def _index_images(folder: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    """``{frame: path}`` of the images in ``folder``; hidden files (``.*``, e.g. macOS
    ``._000001.png``) are skipped, two images of one frame are an error."""
    out: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or p.suffix.lower() not in suffixes or not p.is_file():
            continue
        if p.stem in out:
            raise DatasetError(
                f"{folder}: frame {p.stem} has two images ({out[p.stem].name}, {p.name}); "
                "keep one of them"
            )
        out[p.stem] = p
    return out


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the IEND chunk, always the last 12 bytes
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> channels (3: palette)
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


@dataclass(frozen=True)
class ImageHeader:
    kind: str  # "png" or "jpeg"
    width: int
    height: int
    bit_depth: int
    channels: int


def _unreadable(path: Path, exc: OSError) -> DatasetError:
    return DatasetError(
        f"{path}: cannot be read ({exc.strerror or exc}); check the file and its permissions"
    )


def _read(path: Path, size: int = -1) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(size)
    except OSError as exc:
        raise _unreadable(path, exc) from None


def _ends(path: Path, n_head: int, n_tail: int) -> tuple[bytes, bytes]:
    """The first ``n_head`` and last ``n_tail`` bytes of a file, with one open and no
    read-ahead (a header check touches two pages of each file, not the kernel's window)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError as exc:
        raise _unreadable(path, exc) from None
    try:
        if hasattr(os, "posix_fadvise"):
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_RANDOM)
        head = os.pread(fd, n_head, 0)
        size = os.fstat(fd).st_size
        tail = os.pread(fd, n_tail, size - n_tail) if size >= n_tail else b""
    except OSError as exc:
        raise _unreadable(path, exc) from None
    finally:
        os.close(fd)
    return head, tail


def image_header(path: Path) -> ImageHeader:
    """Size, bit depth and channels of a PNG or JPEG from its first bytes (no decoding).

    PNG files are also checked for their IEND trailer, so a truncated PNG fails here. Only
    the first 64 bytes (a PNG's IHDR) and the last 12 are read; a JPEG's frame header, which
    may follow large metadata, is looked for in its first 64 KiB. Reading 64 KiB of every
    PNG made this check ~15 s of a 32 000-image set not yet in the page cache."""
    head, tail = _ends(path, 64, len(PNG_END))
    if head.startswith(b"\xff\xd8"):
        head = _read(path, 1 << 16)
    if head.startswith(PNG_SIGNATURE):
        if len(head) < 33 or head[12:16] != b"IHDR":
            raise DatasetError(f"{path}: corrupt PNG (no IHDR header); re-export or delete it")
        width, height, depth, ctype = struct.unpack(">IIBB", head[16:26])
        if tail != PNG_END:
            raise DatasetError(
                f"{path}: truncated PNG (the file ends before its IEND chunk); "
                "re-export or delete it"
            )
        return ImageHeader("png", width, height, depth, _PNG_CHANNELS.get(ctype, 0))
    if head.startswith(b"\xff\xd8"):
        i = 2
        while i + 9 < len(head):
            if head[i] != 0xFF:
                break
            marker = head[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            length = struct.unpack(">H", head[i + 2 : i + 4])[0]
            if marker in _JPEG_SOF:
                precision, height, width, comps = struct.unpack(">BHHB", head[i + 4 : i + 10])
                return ImageHeader("jpeg", width, height, precision, comps)
            i += 2 + length
        raise DatasetError(f"{path}: corrupt JPEG (no frame header found); re-export or delete it")
    what = "an empty file" if not head else "neither PNG nor JPEG"
    raise DatasetError(f"{path}: {what}; re-export or delete it")


def _decode(path: Path, flags: int, what: str) -> np.ndarray:
    """Decode a PNG/JPEG so that a damaged file gives one DatasetError line naming it (and no
    libpng/libjpeg/OpenCV chatter on stderr).

    A PNG is decoded straight away (the common layouts by :func:`_png_pixels`, the rest by
    OpenCV), its decoder's complaints kept off stderr (:func:`_libpng_quiet`): libpng checks
    every critical chunk's CRC and the zlib stream itself, so checking them in Python first
    would decode each image twice (inflating cost ~13 ms of a 1280x720 PNG, the CRCs alone
    ~0.8 ms). Only when the decoder fails does :func:`_png_problem` walk the file to name
    the problem."""
    data = _read(path)
    png = data.startswith(PNG_SIGNATURE)
    if png:
        problem = None
    elif data.startswith(b"\xff\xd8"):
        sos, eoi = data.rfind(b"\xff\xda"), data.rfind(b"\xff\xd9")
        problem = None if sos > 0 and eoi > sos else "truncated JPEG (no end-of-image marker)"
    else:
        problem = "an empty file" if not data else "neither PNG nor JPEG"
    if problem is None:
        # OpenCV's log level is process-wide: set and restored under the lock, so that two
        # threads decoding at once (the depth stage's static clouds) cannot leave it silent
        with _STDERR_LOCK:
            level = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
            try:
                with _libpng_quiet() if png else nullcontext():
                    img = _png_pixels(data, flags) if png else None
                    if img is None:
                        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
            except imagecodecs.PngError:
                img = None
            finally:
                cv2.utils.logging.setLogLevel(level)
        if img is not None:
            return img
        problem = (_png_problem(data) if png else None) or f"unreadable or corrupt {what}"
    raise DatasetError(f"{path}: {problem}; re-export or delete it")


# IHDR (bit depth, colour type) -> what imagecodecs' decoder returns as is: 8-bit grey, RGB,
# RGBA and 16-bit grey (depth). Palette, grey+alpha, 16-bit colour and sub-byte depths go
# through OpenCV, which expands and scales them.
_PNG_FAST_LAYOUTS = {b"\x08\x00", b"\x08\x02", b"\x08\x06", b"\x10\x00"}
_TO_GRAY = {3: cv2.COLOR_RGB2GRAY, 4: cv2.COLOR_RGBA2GRAY}
_TO_BGR = {3: cv2.COLOR_RGB2BGR, 4: cv2.COLOR_RGBA2BGR}
_TO_UNCHANGED = {3: cv2.COLOR_RGB2BGR, 4: cv2.COLOR_RGBA2BGRA}


def _png_pixels(data: bytes, flags: int) -> np.ndarray | None:
    """A PNG decoded as ``cv2.imdecode(data, flags)`` would (BGR order, grey by OpenCV's
    weights), by imagecodecs' libpng with zlib-ng: 17-25 % faster than OpenCV's bundled
    decoder at 848x480-1280x720 (docs/benchmarks.md), and every image of a calibration is
    decoded at least once. None for a layout it does not handle as is; raises
    ``imagecodecs.PngError`` for a damaged stream."""
    if flags not in (cv2.IMREAD_UNCHANGED, cv2.IMREAD_GRAYSCALE, cv2.IMREAD_COLOR):
        return None
    if data[12:16] != b"IHDR" or (data[24:25] + data[25:26]) not in _PNG_FAST_LAYOUTS:
        return None
    img = imagecodecs.png_decode(data)
    channels = 1 if img.ndim == 2 else img.shape[2]
    if flags == cv2.IMREAD_UNCHANGED:
        return img if channels == 1 else cv2.cvtColor(img, _TO_UNCHANGED[channels])
    if img.dtype != np.uint8:  # 16-bit grey read as 8-bit: OpenCV keeps the high byte
        img = (img >> 8).astype(np.uint8)
    if flags == cv2.IMREAD_GRAYSCALE:
        return img if channels == 1 else cv2.cvtColor(img, _TO_GRAY[channels])
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR if channels == 1 else _TO_BGR[channels])


def _png_problem(data: bytes) -> str | None:
    """What is structurally wrong with a PNG (chunk lengths, CRCs, IEND, its zlib stream), or
    None."""
    i = len(PNG_SIGNATURE)
    inflater = zlib.decompressobj()
    while i + 12 <= len(data):
        length = struct.unpack(">I", data[i : i + 4])[0]
        kind = data[i + 4 : i + 8]
        end = i + 12 + length
        if end > len(data):
            break
        crc = struct.unpack(">I", data[end - 4 : end])[0]
        if zlib.crc32(data[i + 4 : end - 4]) != crc:
            return f"corrupt PNG (CRC error in a {kind.decode('latin-1')!r} chunk)"
        if kind == b"IDAT":
            try:  # libpng would print its own complaint to stderr; find it here instead
                inflater.decompress(data[i + 8 : end - 4])
            except zlib.error:
                return "corrupt PNG (damaged compressed image data)"
        if kind == b"IEND":
            return None if inflater.eof else "corrupt PNG (its image data ends early)"
        i = end
    return "truncated PNG (the file ends before its IEND chunk)"


_STDERR_LOCK = threading.Lock()
_LIBPNG_CHATTER = (b"libpng ", b"PNG warning: ", b"PNG error: ")  # OpenCV's, imagecodecs'


@contextmanager
def _libpng_quiet() -> Iterator[None]:
    """File descriptor 2 goes to a temporary file for the block; afterwards what was written
    there, minus libpng's own lines, goes to the real stderr. libpng prints its errors itself
    (OpenCV's log level does not reach it); other threads' output is delayed, not lost."""
    with tempfile.TemporaryFile() as tmp:  # the caller holds _STDERR_LOCK
        saved = os.dup(2)
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            lines = tmp.read().splitlines(keepends=True)
            kept = b"".join(ln for ln in lines if not ln.startswith(_LIBPNG_CHATTER))
            if kept:
                os.write(2, kept)


def _check_size(
    path: Path, size: tuple[int, int], width: int, height: int, depth: bool = False
) -> None:
    """A colour image (or depth aligned to it) must have the intrinsics' ``width x height``."""
    if tuple(size) == (width, height):
        return
    if depth:
        raise DatasetError(
            f"{path}: depth is {size[0]}x{size[1]} but the colour intrinsics say "
            f"{width}x{height}; align depth to colour first"
        )
    raise DatasetError(
        f"{path}: image is {size[0]}x{size[1]} but rig.yaml says {width}x{height}; "
        "use the intrinsics of this resolution"
    )


def read_color_image(path: Path, width: int, height: int, gray: bool = False) -> np.ndarray:
    """Decode an 8-bit colour image and check its size against the intrinsics."""
    img = _decode(Path(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR, "image")
    _check_size(path, (img.shape[1], img.shape[0]), width, height)
    return img


def read_depth_image(path: Path, width: int, height: int) -> np.ndarray:
    """Decode a 16-bit single-channel depth PNG and check its size."""
    img = _decode(Path(path), cv2.IMREAD_UNCHANGED, "depth image")
    if img.dtype != np.uint16 or img.ndim != 2:
        kind = f"{img.dtype}, {1 if img.ndim == 2 else img.shape[2]} channel(s)"
        raise DatasetError(
            f"{path}: depth must be a 16-bit single-channel PNG, got {kind}; "
            "export raw depth counts (z16) aligned to colour"
        )
    _check_size(path, (img.shape[1], img.shape[0]), width, height, depth=True)
    return img


# --------------------------------------------------------------------------- writing
PNG_COMPRESSION = 1  # fastest zlib level: sets are large, written once and read a few times


def encode_png(image: np.ndarray, where: Path | str) -> bytes:
    """``image`` (8-bit colour or grey, 16-bit depth) as PNG bytes; ``where`` names the file
    in the error."""
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:
        raise DatasetError(f"{where}: could not encode the image as PNG")
    return buf.tobytes()


def write_png(path: Path, image: np.ndarray) -> None:
    Path(path).write_bytes(encode_png(image, path))


@contextmanager
def staged_folder(out: Path) -> Iterator[Path]:
    """A temporary sibling of ``out`` to write a dataset into, renamed to ``out`` (absent or
    empty) when the block ends and deleted when it raises: ``out`` never holds half a set."""
    out = Path(out)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        yield tmp
        with sigint_deferred():
            if out.exists():
                out.rmdir()
            tmp.rename(out)
            mark_committed(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


class FolderWriter:
    """Writes the folder form: ``rig.yaml`` at once, then ``<camera>/color/<frame>.png`` and
    ``<camera>/depth/<frame>.png`` (8-bit colour, 16-bit depth counts aligned to colour) and,
    where the source has them, ``<camera>/timestamps.csv`` (each colour frame's capture time).

    ``depth_cameras`` get a ``depth/`` folder (default: every camera). :meth:`write` puts one
    image in place and :meth:`write_timestamps` a camera's times, for a folder that is
    published whole (:func:`staged_folder`); :meth:`write_set` puts a whole set (with its
    times) in place at once, for a folder read while it grows."""

    def __init__(self, root: Path, rig: Rig, depth_cameras: Iterable[str] | None = None):
        self.root = Path(root)
        with_depth = set(rig.names if depth_cameras is None else depth_cameras)
        for name in rig.names:
            (self.root / name / "color").mkdir(parents=True, exist_ok=True)
            if name in with_depth:
                (self.root / name / "depth").mkdir(parents=True, exist_ok=True)
        save_rig(rig, self.root / "rig.yaml")
        self.sets_written = 0  # by write_set
        self._times: dict[str, dict[str, float]] = {}  # camera -> frame -> t_ms written

    def path(self, camera: str, kind: str, frame: str) -> Path:
        """Where frame ``frame`` of ``camera`` goes; ``kind`` is "color" or "depth"."""
        return self.root / camera / kind / f"{frame}.png"

    def write(self, camera: str, kind: str, frame: str, image: np.ndarray) -> None:
        write_png(self.path(camera, kind, frame), image)

    def write_timestamps(self, camera: str, times_ms: dict[str, float]) -> None:
        """``<camera>/timestamps.csv`` with ``frame -> t_ms`` added to the times already
        written for ``camera`` (the file is replaced whole, never half written)."""
        tmp, final = self._stage_timestamps(camera, times_ms)
        os.replace(tmp, final)

    def _stage_timestamps(self, camera: str, times_ms: dict[str, float]) -> tuple[Path, Path]:
        table = {**self._times.get(camera, {}), **{f: float(t) for f, t in times_ms.items()}}
        final = self.root / camera / TIMESTAMPS_FILE
        tmp = final.with_name(f".{TIMESTAMPS_FILE}.tmp")
        tmp.write_text(timestamps_csv_text(table))
        self._times[camera] = table
        return tmp, final

    def write_set(
        self, frame: str, colors: dict[str, np.ndarray], depths: dict[str, np.ndarray],
        times_ms: dict[str, float] | None = None,
    ) -> None:
        """One synchronised set, all of it or none: every file is written under a temporary
        name first, then all are renamed with Ctrl-C held back (a Ctrl-C meanwhile is raised
        once the set is complete and counted in :attr:`sets_written`). ``times_ms`` (camera
        -> capture time of its colour frame, ms) adds the set's row to those cameras'
        ``timestamps.csv``, renamed with the images."""
        staged: list[tuple[Path, Path]] = []
        before, committed = {c: dict(t) for c, t in self._times.items()}, False
        try:
            for camera, color in colors.items():
                parts = [("color", color)] + (
                    [("depth", depths[camera])] if camera in depths else []
                )
                for kind, image in parts:
                    final = self.path(camera, kind, frame)
                    tmp = final.with_name(f".{frame}.png.tmp")  # not a .png: readers skip it
                    staged.append((tmp, final))
                    tmp.write_bytes(encode_png(image, final))
            for camera, t_ms in (times_ms or {}).items():
                if camera in colors:
                    staged.append(self._stage_timestamps(camera, {frame: t_ms}))
            with sigint_deferred():
                for tmp, final in staged:
                    os.replace(tmp, final)
                self.sets_written += 1
                committed = True
        except BaseException:
            if not committed:  # the set is not written: nor are its times
                self._times = before
            raise
        finally:
            for tmp, _ in staged:
                tmp.unlink(missing_ok=True)
