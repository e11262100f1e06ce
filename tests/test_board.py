"""Printed boards: the real pose2sim chessboard images against Qualisys, and synthetic
ChArUco and circle-grid images against the homography that made them."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibkit.calibrate.board import Board, find_board, parse_board
from calibkit.core.errors import UserError

DATA = Path(__file__).resolve().parent.parent / "fixtures" / "pose2sim_chessboard_4cam"


def _qualisys_focal_px(camera: str) -> tuple[float, float]:
    """focalLengthU/V of one camera in Calib.qca.txt, in pixels (Qualisys units / 64)."""
    text = (DATA / "Calib.qca.txt").read_text()
    block = text[text.index(f'serial="{camera}"'):]
    m = re.search(r'focalLengthU="([\d.]+)" focalLengthV="([\d.]+)"', block)
    assert m is not None
    return float(m[1]) / 64.0, float(m[2]) / 64.0


def test_real_chessboard_matches_qualisys(calibkit_cli, tmp_path):
    fu, fv = _qualisys_focal_px("cam01")
    out = tmp_path / "cam01.json"
    r = calibkit_cli("intrinsic", "--images", DATA / "intrinsics" / "int_cam01_img",
                     "--board", "chessboard:4x7:60", "--camera", "cam01", "--fix-k3",
                     "--json", out, "--rig", tmp_path / "rig.toml")
    assert r.code == 0, r.err
    data = json.loads(out.read_text())
    assert abs(data["fx"] / fu - 1) < 0.015 and abs(data["fy"] / fv - 1) < 0.015
    assert data["views"] == 6  # OpenCV finds the board in 6 of the 7 images
    assert "cam01_02_int.jpg" in r.err
    assert data["rms_px"] < 0.5
    # the principal point of a 1088 x 1920 portrait image lies near its centre
    assert abs(data["cx"] - 543.5) < 60 and abs(data["cy"] - 959.5) < 60


def _warped(board_img: np.ndarray, size=(800, 600), seed=0):
    """The board image seen through a random tilt: (image, homography board px -> image)."""
    rng = np.random.default_rng(seed)
    h, w = board_img.shape[:2]
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = np.float32([[100, 80], [700, 60], [720, 540], [80, 520]])
    dst += rng.uniform(-30, 30, dst.shape).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, dst)
    img = cv2.warpPerspective(board_img, H, size, flags=cv2.INTER_LINEAR, borderValue=255)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    return img, H


def _apply(H, pts):
    p = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    return p[:, :2] / p[:, 2:]


def test_charuco_board_found_where_the_homography_puts_it():
    board = parse_board("charuco:6x5:40:30")
    aruco = cv2.aruco
    cb = aruco.CharucoBoard((6, 5), 0.040, 0.030,
                            aruco.getPredefinedDictionary(aruco.DICT_4X4_50))
    px_per_m = 5000.0  # the board drawn at 200 px per 40 mm square
    art = cb.generateImage((int(6 * 0.04 * px_per_m), int(5 * 0.04 * px_per_m)))
    img, H = _warped(art)
    view = find_board(img, board)
    assert view is not None and len(view) >= 15
    expected = _apply(H, view.obj[:, :2] * px_per_m - 0.5)
    assert np.abs(view.uv - expected).max() < 0.5


def test_circle_grid_found_where_the_homography_puts_it():
    board = parse_board("circles:5x4:30")
    s = 80  # px per 30 mm
    art = np.full((5 * s, 6 * s), 255, np.uint8)
    centres = board.object_points()[:, :2] / 0.030 * s + s
    for x, y in centres:
        cv2.circle(art, (int(x * 16), int(y * 16)), 16 * 22, 0, -1, cv2.LINE_AA, 4)
    img, H = _warped(art, seed=1)
    view = find_board(img, board)
    assert view is not None and len(view) == 20
    # circle centres are not projective invariants: allow the tilt's bias (~0.1 px)
    assert np.abs(view.uv - _apply(H, centres)).max() < 0.5


def test_board_not_found_and_bad_specs():
    blank = np.full((240, 320), 128, np.uint8)
    assert find_board(blank, Board("chessboard", 4, 7, 60)) is None
    for bad in ("chessboard:4x7", "chessboard:4by7:60", "hexagons:4x7:60",
                "charuco:5x7:40:50", "charuco:5x7:40:30:DICT_NOPE", "circles:4x11:20:odd"):
        with pytest.raises(UserError):
            parse_board(bad)
    assert parse_board("circles:4x11:20:asym").asymmetric


def test_images_without_a_board(calibkit_cli, tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((120, 160), 90, np.uint8))
    r = calibkit_cli("intrinsic", "--images", tmp_path, "--board", "chessboard:9x6:25")
    assert r.code == 2 and "too few usable views" in r.err
