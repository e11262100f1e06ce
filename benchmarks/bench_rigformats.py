"""Other tools' calibrations read in: are the conventions right, and what does reading cost?

Three tables, from the real files in fixtures/:

1. caliscope's pose convention. caliscope's stereo-triangulated board corners
   (stereotriangulated_points.csv, metres) projected through the imported rig, against the
   pixels caliscope stored for them: median and 95th percentile per camera (px). Baseline in
   the same run: the same file read the other way (rotation/translation as camera-to-world).
2. QTM's distortion units. Camera cam01's chessboard photos (fixtures/pose2sim_chessboard_4cam,
   4x7 corners, 60 mm) calibrated by OpenCV with QTM's K held fixed: the k1, k2 the photos
   give, against the .qca's coefficients as they are and divided by 64 (Pose2Sim's reading);
   then the board's reprojection RMS with each set held (only the board poses fitted).
3. Reading speed: median over repeats of reading each file into a Rig (ms); baseline
   Rig.load of our own rig.toml with the same cameras.

    python benchmarks/bench_rigformats.py [--repeats 20]
"""

from __future__ import annotations

import argparse
import csv
import glob
import tempfile
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table
from calibkit.core.camera import Rig
from calibkit.core.rigformats import read_rig_file
from calibkit.core.rigformats.caliscope import read_caliscope
from calibkit.core.rigformats.qca import read_qca

ROOT = Path(__file__).resolve().parents[1]
CALISCOPE = ROOT / "fixtures" / "caliscope_4cam"
QTM = ROOT / "fixtures" / "pose2sim_chessboard_4cam"


def caliscope_table() -> None:
    rig = read_caliscope(CALISCOPE / "camera_array.toml")
    inverted = Rig(tuple(c.replace(R=c.R.T, t=c.centre) for c in rig))
    with open(CALISCOPE / "calibration" / "extrinsic" / "stereotriangulated_points.csv",
              newline="") as handle:
        rows = list(csv.DictReader(handle))
    col = {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k not in ("", "pair")}
    xyz = np.stack([col["x_pos"], col["y_pos"], col["z_pos"]], axis=1)
    out = []
    for cam in rig:
        cam_id = int(cam.name.removeprefix("cam_"))
        figures = []
        for reading in (rig, inverted):
            errs = []
            for side in "AB":
                sel = col[f"cam_id_{side}"] == cam_id
                uv, _ = reading[cam.name].project(xyz[sel])
                seen = np.stack([col[f"x_{side}"][sel], col[f"y_{side}"][sel]], axis=1)
                errs.append(np.linalg.norm(uv - seen, axis=1))
            err = np.concatenate(errs)
            figures += [np.median(err), np.percentile(err, 95)]
        out.append([cam.name, len(err), *(f"{v:.2f}" for v in figures)])
    print("caliscope: its triangulated points reprojected through the imported rig (px)")
    print_table(out, ["camera", "points", "median w2c", "p95 w2c", "median c2w (baseline)",
                      "p95 c2w (baseline)"])


def qtm_table() -> None:
    # deferred on purpose: only this table needs OpenCV
    import cv2

    cam = read_qca(QTM / "Calib.qca.txt")["cam01"]
    board = np.zeros((28, 3), np.float32)
    board[:, :2] = np.mgrid[0:4, 0:7].T.reshape(-1, 2) * 60.0
    objects, images = [], []
    for name in sorted(glob.glob(str(QTM / "intrinsics" / "*" / "*.jpg"))):
        gray = cv2.imread(name, cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(gray, (4, 7))
        if found:
            corners = cv2.cornerSubPix(gray, corners, (7, 7), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30,
                                        1e-3))
            objects.append(board)
            images.append(corners)
    fixed_k = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_FOCAL_LENGTH
               | cv2.CALIB_FIX_PRINCIPAL_POINT)
    size = cam.size
    rms, _, fitted, _, _ = cv2.calibrateCamera(objects, images, size, cam.K.copy(), np.zeros(5),
                                               flags=fixed_k | cv2.CALIB_FIX_K3)
    fitted = fitted.ravel()
    held = fixed_k | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 \
        | cv2.CALIB_FIX_TANGENT_DIST
    rows = [["fitted to the photos (K held)", f"{fitted[0]:.4f}", f"{fitted[1]:.4f}",
             f"{rms:.3f}"]]
    for label, dist in (("file as it is (read here)", cam.dist),
                        ("file / 64 (Pose2Sim)", cam.dist / 64), ("none", np.zeros(5))):
        rms_held, *_ = cv2.calibrateCamera(objects, images, size, cam.K.copy(),
                                           dist.astype(np.float64).copy(), flags=held)
        rows.append([label, f"{dist[0]:.4f}", f"{dist[1]:.4f}", f"{rms_held:.3f}"])
    print(f"\nQTM cam01: k1, k2 and the board's reprojection RMS ({len(images)} photos, "
          f"{size[0]}x{size[1]})")
    print_table(rows, ["distortion", "k1", "k2", "board RMS px"])


def speed_table(repeats: int) -> None:
    files = [("caliscope", CALISCOPE / "camera_array.toml"), ("qca", QTM / "Calib.qca.txt")]
    with tempfile.TemporaryDirectory() as tmp:
        rig = read_qca(QTM / "Calib.qca.txt")
        own = Path(tmp) / "rig.toml"
        rig.save(own)
        rows = []
        for label, path, read in ([("rig.toml (baseline)", own, Rig.load)]
                                  + [(f, p, lambda p, f=f: read_rig_file(p, f)) for f, p in files]
                                  + [("auto-detected qca", QTM / "Calib.qca.txt",
                                      lambda p: read_rig_file(p, "auto"))]):
            read(path)  # warm imports and caches
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                read(path)
                times.append(time.perf_counter() - t0)
            rows.append([label, f"{np.median(times) * 1e3:.2f}", f"{max(times) * 1e3:.2f}"])
    print(f"\nreading a 4-camera file into a Rig ({repeats} repeats)")
    print_table(rows, ["file", "median ms", "max ms"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    caliscope_table()
    qtm_table()
    speed_table(args.repeats)


if __name__ == "__main__":
    main()
