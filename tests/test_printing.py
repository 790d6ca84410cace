"""Printed sheets: true scale, marker placement per face, page choice and the back-face winding.

Each printed file is rasterised, its markers detected with OpenCV, and every detected corner
mapped from pixels to page mm and back into the board frame with the sheet mapping of
docs/formats.md (mirrored in x for the back sheet, which is seen from -z). Pixel centres follow
OpenCV: pixel (0, 0) is centred at (0, 0), so page_mm = (px + 0.5) * mm_per_px.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pypdfium2 as pdfium
import pytest
import yaml
from PIL import Image

from rgbd_calib.core.errors import BoardError
from rgbd_calib.model.board import BACK, FRONT, Board, board_from_grid
from rgbd_calib.model.board_file import load_board
from rgbd_calib.outputs.printing import PrintResult, write_printable_board

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
CORNER_TOL_MM = 0.1  # detected corner vs board corner, after pixel -> page -> board mapping
PAGE_TOL_MM = 0.1
WINDING_MIN_MM = 10.0  # a mirrored corner order misses by about half a marker (20 mm)
PDF_RENDER_DPI = 400  # 1 px = 0.0635 mm on a noise-free raster
PNG_DPI = 300
A3_LANDSCAPE_MM = (420.0, 297.0)
FACES = {FRONT: "front", BACK: "back"}


@pytest.fixture(scope="module")
def thesis() -> Board:
    return load_board(CONFIGS / "board_thesis.yaml")


@pytest.fixture(scope="module")
def printed(thesis: Board, tmp_path_factory: pytest.TempPathFactory) -> PrintResult:
    return write_printable_board(thesis, tmp_path_factory.mktemp("print"), dpi=PNG_DPI)


def render_pdf(path: Path, page_index: int = 0, dpi: int = PDF_RENDER_DPI):
    """Greyscale raster of one PDF page, the page size in mm and the true mm per pixel (x, y).

    pypdfium2 stretches the page onto ceil(size * scale) pixels, so the pixel pitch is taken
    from the bitmap size rather than from ``dpi`` (they differ by < 0.05 %)."""
    page = pdfium.PdfDocument(path)[page_index]
    size_mm = tuple(s * 25.4 / 72.0 for s in page.get_size())
    img = page.render(scale=dpi / 72.0, grayscale=True).to_numpy()
    pitch = np.array([size_mm[0] / img.shape[1], size_mm[1] / img.shape[0]])
    assert np.allclose(pitch, 25.4 / dpi, rtol=5e-4)
    return img, size_mm, pitch


def detect(board: Board, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ids ``(N,)`` and pixel corners ``(N,4,2)`` with subpixel refinement."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(board.aruco_dict, params, cv2.aruco.RefineParameters())
    corners, ids, _ = detector.detectMarkers(img)
    assert ids is not None, "no marker detected"
    return np.asarray(ids).ravel(), np.asarray(corners, dtype=float).reshape(-1, 4, 2)


def page_mm_to_board_mm(board: Board, face: int, uv_mm: np.ndarray,
                        page_size_mm: tuple[float, float]) -> np.ndarray:
    """Inverse of the sheet mapping: page mm (top-left origin, v down) -> board x, y in mm."""
    xmin, xmax, ymin, ymax = (v * 1000.0 for v in board.panel)
    off_u = (page_size_mm[0] - (xmax - xmin)) / 2.0
    off_v = (page_size_mm[1] - (ymax - ymin)) / 2.0
    u, v = uv_mm[..., 0] - off_u, uv_mm[..., 1] - off_v
    x = xmin + u if face == FRONT else xmax - u
    return np.stack([x, ymax - v], axis=-1)


def corner_errors_mm(board: Board, face: int, img: np.ndarray, pitch: np.ndarray,
                     page_size_mm: tuple[float, float]) -> np.ndarray:
    """Per-corner distance (mm) between detected and board corners; checks the id set."""
    ids, px = detect(board, img)
    assert sorted(ids.tolist()) == sorted(board.face_ids(face).tolist()), (
        f"{FACES[face]} sheet: detected ids {sorted(ids.tolist())}")
    board_mm = page_mm_to_board_mm(board, face, (px + 0.5) * pitch, page_size_mm)
    expected_mm = board.object_points(ids)[:, :, :2] * 1000.0
    return np.linalg.norm(board_mm - expected_mm, axis=-1)


@pytest.mark.parametrize("face", [FRONT, BACK])
def test_pdf_markers_at_board_corners(thesis: Board, printed: PrintResult, face: int) -> None:
    img, size_mm, pitch = render_pdf(printed.sheet(face).pdf)
    err = corner_errors_mm(thesis, face, img, pitch, size_mm)
    assert err.max() < CORNER_TOL_MM, f"max {err.max():.4f} mm, mean {err.mean():.4f} mm"
    # the combined PDF carries the same page for this face
    page = 0 if face == FRONT else 1
    img2, size2, pitch2 = render_pdf(printed.files[-1], page)
    assert printed.files[-1].name == "board.pdf"
    assert corner_errors_mm(thesis, face, img2, pitch2, size2).max() < CORNER_TOL_MM


@pytest.mark.parametrize("face", [FRONT, BACK])
def test_png_markers_at_board_corners(thesis: Board, printed: PrintResult, face: int) -> None:
    with Image.open(printed.sheet(face).png) as im:
        dpi = im.info["dpi"]  # from the pHYs chunk (pixels per metre: 300 dpi reads 299.9994)
        img = np.asarray(im.convert("L"))
    assert dpi[0] == pytest.approx(PNG_DPI, abs=0.01) and dpi[1] == pytest.approx(dpi[0])
    pitch = np.array([25.4 / dpi[0], 25.4 / dpi[1]])
    err = corner_errors_mm(thesis, face, img, pitch, printed.page_size_mm)
    assert err.max() < CORNER_TOL_MM, f"max {err.max():.4f} mm, mean {err.mean():.4f} mm"


def test_page_size_and_too_small_page(thesis: Board, printed: PrintResult,
                                      tmp_path: Path) -> None:
    assert printed.page_name == "A3-landscape"
    for path in {s.pdf for s in printed.sheets} | {printed.files[-1]}:
        doc = pdfium.PdfDocument(path)
        assert len(doc) == (2 if path.name == "board.pdf" else 1)
        for page in doc:
            size_mm = [s * 25.4 / 72.0 for s in page.get_size()]
            assert size_mm == pytest.approx(A3_LANDSCAPE_MM, abs=PAGE_TOL_MM), path.name
    assert printed.page_size_mm == pytest.approx(A3_LANDSCAPE_MM, abs=PAGE_TOL_MM)

    with pytest.raises(BoardError) as exc:
        write_printable_board(thesis, tmp_path / "a4", page="A4")
    assert "\n" not in str(exc.value) and "A4" in str(exc.value)
    assert not (tmp_path / "a4").exists()

    small = board_from_grid("DICT_4X4_50", 2, 3, 0.03, 0.01, 0.003, 0, 6)  # 110 x 70 mm
    assert write_printable_board(small, tmp_path / "small", dpi=72).page_name == "A4-portrait"


def test_back_sheet_winding_is_mirror_of_table_4_2(thesis: Board,
                                                   printed: PrintResult) -> None:
    """An affine map board (x, y) -> back-sheet pixels fits the detection-order corners to
    < 0.1 mm, and misses every corner by >= 10 mm with the thesis Table 4.2's back corners
    taken as listed: the table's back-face order is the mirror of what ArUco detects."""
    img, _, pitch = render_pdf(printed.sheet(BACK).pdf)
    ids, px = detect(thesis, img)
    assert set(ids.tolist()) == set(thesis.face_ids(BACK).tolist())

    def residuals_mm(board_xy_mm: np.ndarray) -> np.ndarray:
        A = np.column_stack([board_xy_mm.reshape(-1, 2), np.ones(px.size // 2)])
        M, *_ = np.linalg.lstsq(A, px.reshape(-1, 2), rcond=None)
        return np.linalg.norm((px.reshape(-1, 2) - A @ M) * pitch, axis=-1)

    detection_order = thesis.object_points(ids)[:, :, :2] * 1000.0
    assert residuals_mm(detection_order).max() < CORNER_TOL_MM

    raw = yaml.safe_load((CONFIGS / "board_thesis_table42.yaml").read_text())
    table = np.array([raw["markers"][int(i)] for i in ids], dtype=float)[:, :, :2] * 1000.0
    # same squares, only the order of the corners differs
    assert np.allclose(np.sort(table, axis=1), np.sort(detection_order, axis=1))
    assert residuals_mm(table).min() >= WINDING_MIN_MM


def test_panel_centred_on_larger_page(thesis: Board, tmp_path: Path) -> None:
    result = write_printable_board(thesis, tmp_path, dpi=72, page="A2-landscape")
    assert result.page_size_mm == pytest.approx((594.0, 420.0))
    for face in (FRONT, BACK):
        img, size_mm, pitch = render_pdf(result.sheet(face).pdf, dpi=200)
        assert corner_errors_mm(thesis, face, img, pitch, size_mm).max() < CORNER_TOL_MM


@pytest.mark.parametrize("face", [FRONT, BACK])
def test_quiet_zone_and_alignment_marks(thesis: Board, printed: PrintResult, face: int) -> None:
    """One marker module around every marker is blank paper, and the crosshairs sit at the
    panel's corners and edge midpoints, the same board points on both sheets."""
    with Image.open(printed.sheet(face).png) as im:
        img = np.asarray(im.convert("L"))
    px_per_mm = PNG_DPI / 25.4
    module_mm = thesis.marker_length * 1000.0 / (thesis.bits + 2)
    sheet = printed.sheet(face)
    for quad in sheet.corners_page_mm:
        lo, hi = quad.min(axis=0), quad.max(axis=0)
        o0 = np.floor((lo - module_mm) * px_per_mm).astype(int) + 1
        o1 = np.ceil((hi + module_mm) * px_per_mm).astype(int) - 1
        i0 = np.floor(lo * px_per_mm).astype(int) - 1
        i1 = np.ceil(hi * px_per_mm).astype(int) + 1
        ring = img[o0[1]:o1[1], o0[0]:o1[0]].copy()
        ring[i0[1] - o0[1]:i1[1] - o0[1], i0[0] - o0[0]:i1[0] - o0[0]] = 255
        assert ring.min() == 255, f"ink in the quiet zone of a marker at {lo} mm"

    xmin, xmax, ymin, ymax = (v * 1000.0 for v in thesis.panel)
    xm, ym = (xmin + xmax) / 2, (ymin + ymax) / 2
    marks = [(xmin, ymin), (xmax, ymin), (xmin, ymax), (xmax, ymax), (xm, ymin), (xm, ymax),
             (xmin, ym), (xmax, ym)]
    W, H = printed.page_size_mm
    off = np.array([W - (xmax - xmin), H - (ymax - ymin)]) / 2.0
    for x, y in marks:
        u = (x - xmin) if face == FRONT else (xmax - x)
        col, row = np.clip(((off + [u, ymax - y]) * px_per_mm).astype(int), 0,
                           np.array(img.shape[::-1]) - 1)
        assert img[row, col] < 128, f"no alignment mark at board ({x}, {y}) mm"


def test_the_board_command_says_what_the_printed_sheet_should_measure(thesis: Board) -> None:
    """A print a fraction of a percent off scales every translation: `board` says what to
    measure on the printed front sheet and what it should read (the thesis board's 7 x 4
    markers of 40 mm, 20 mm apart: 400 x 220 mm), and where the measurement goes."""
    from rgbd_calib.outputs.printing import measuring_line

    line = measuring_line(thesis)
    assert "outermost marker corners should span 400.0 mm across and 220.0 mm down" in line
    assert "print_scale_sigma" in line and "\n" not in line
    charuco = load_board(Path(__file__).parents[1] / "configs" / "board_charuco_a3.yaml")
    assert "inner chessboard corners" in measuring_line(charuco)
    cube = load_board(Path(__file__).parents[1] / "configs" / "board_cube.yaml")
    assert measuring_line(cube) is None
