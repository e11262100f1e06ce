"""Printed calibration boards in images: chessboard, ChArUco and circle grids -> plane views.

For users who have a printed board instead of a monitor. A board is given as one string,
`KIND:COLSxROWS:SIZE_MM[:...]`:
- `chessboard:4x7:60`: 4 x 7 inner corners, 60 mm squares;
- `charuco:5x7:40:30[:DICT]`: 5 x 7 squares of 40 mm, markers of 30 mm, dictionary
  (default DICT_4X4_50), as cv2.aruco draws it;
- `circles:4x11:20[:asym]`: a grid of 4 x 11 circle centres 20 mm apart (asymmetric
  when `asym`, as OpenCV's acircles pattern).
Each image where the board is found becomes a PlaneView (calibkit.calibrate.intrinsic).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibkit.calibrate.intrinsic import PlaneView
from calibkit.cameras.images import IMAGE_SUFFIXES, image_files
from calibkit.core.errors import UserError
from calibkit.vision.gray import to_gray


@dataclass(frozen=True)
class Board:
    kind: str  # "chessboard", "charuco", "circles"
    cols: int
    rows: int
    size_mm: float
    marker_mm: float = 0.0
    dictionary: str = "DICT_4X4_50"
    asymmetric: bool = False

    def object_points(self) -> np.ndarray:
        """(cols*rows, 3) board points in metres, in the order OpenCV reports them."""
        s = self.size_mm / 1000.0
        if self.kind == "circles" and self.asymmetric:
            pts = [((2 * c + r % 2) * s, r * s) for r in range(self.rows)
                   for c in range(self.cols)]
            return np.array([[x, y, 0.0] for x, y in pts])
        gx, gy = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.column_stack([gx.ravel() * s, gy.ravel() * s, np.zeros(gx.size)])


def parse_board(spec: str) -> Board:
    parts = spec.strip().split(":")
    usage = ("--board takes chessboard:COLSxROWS:SQUARE_MM, charuco:COLSxROWS:SQUARE_MM:"
             f"MARKER_MM[:DICT] or circles:COLSxROWS:SPACING_MM[:asym]; got {spec!r}")
    if len(parts) < 3:
        raise UserError(usage)
    kind = parts[0].lower()
    try:
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        size = float(parts[2])
    except ValueError:
        raise UserError(usage) from None
    if cols < 2 or rows < 2 or size <= 0:
        raise UserError(f"--board needs at least 2x2 points and a positive size; got {spec!r}")
    if kind == "chessboard" and len(parts) == 3:
        return Board(kind, cols, rows, size)
    if kind == "circles" and len(parts) in (3, 4):
        asym = len(parts) == 4 and parts[3].lower() in ("asym", "asymmetric")
        if len(parts) == 4 and not asym:
            raise UserError(usage)
        return Board(kind, cols, rows, size, asymmetric=asym)
    if kind == "charuco" and len(parts) in (4, 5):
        try:
            marker = float(parts[3])
        except ValueError:
            raise UserError(usage) from None
        dictionary = parts[4].upper() if len(parts) == 5 else "DICT_4X4_50"
        if not hasattr(cv2.aruco, dictionary):
            raise UserError(f"unknown ArUco dictionary {dictionary!r} (e.g. DICT_4X4_50)")
        if not 0 < marker < size:
            raise UserError("a ChArUco marker must be smaller than its square")
        return Board(kind, cols, rows, size, marker, dictionary)
    raise UserError(usage)


def find_board(image: np.ndarray, board: Board) -> PlaneView | None:
    """The board's points in one image, or None when it is not (wholly) found."""
    gray = to_gray(image)
    if board.kind == "chessboard":
        pattern = (board.cols, board.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
        if not ok:
            return None
        # refine within a window a third of the smallest corner spacing
        c = corners.reshape(board.rows, board.cols, 2)
        spacing = min(np.linalg.norm(np.diff(c, axis=0), axis=2).min(),
                      np.linalg.norm(np.diff(c, axis=1), axis=2).min())
        win = int(np.clip(spacing / 3, 3, 15))
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), crit)
        return PlaneView(board.object_points(), corners.reshape(-1, 2).astype(np.float64))
    if board.kind == "circles":
        flags = cv2.CALIB_CB_ASYMMETRIC_GRID if board.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
        ok, centres = cv2.findCirclesGrid(gray, (board.cols, board.rows), flags=flags)
        if not ok:
            ok, centres = cv2.findCirclesGrid(255 - gray, (board.cols, board.rows), flags=flags)
        if not ok:
            return None
        return PlaneView(board.object_points(), centres.reshape(-1, 2).astype(np.float64))
    # ChArUco: corners are identified individually, so a partly visible board still counts
    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(getattr(aruco, board.dictionary))
    cb = aruco.CharucoBoard((board.cols, board.rows), board.size_mm / 1000.0,
                            board.marker_mm / 1000.0, dictionary)
    det = aruco.CharucoDetector(cb)
    corners, ids, _, _ = det.detectBoard(gray)
    if ids is None or len(ids) < 6:
        return None
    obj = np.asarray(cb.getChessboardCorners(), np.float64)[ids.ravel()]
    return PlaneView(obj, corners.reshape(-1, 2).astype(np.float64))


def board_views(folder: str | Path, board: Board, progress=None
                ) -> tuple[list[PlaneView], tuple[int, int], list[str]]:
    """Views of the board in every image of a folder; the image size; the files it was not
    found in."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: no such folder of images")
    files = image_files(folder)
    if not files:
        raise UserError(f"{folder}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    views, missed, size = [], [], None
    for i, path in enumerate(files):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise UserError(f"{path}: not a readable image")
        this = (image.shape[1], image.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise UserError(f"{path} is {this[0]}x{this[1]} but the first image is "
                            f"{size[0]}x{size[1]}: one camera's images only")
        view = find_board(image, board)
        if view is None:
            missed.append(path.name)
        else:
            views.append(PlaneView(view.obj, view.uv, path.name))
        if progress is not None:
            progress(i + 1, len(files))
    assert size is not None
    return views, size, missed
