"""The examples/ programs: their geometry against closed-form truth, and each run against
`mocapd start --sim` as a user runs it."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

import head_tracking as ht  # noqa: E402
import paint3d  # noqa: E402

# a 0.6 x 0.34 m screen standing at y = -3 m, facing +y (into the tracked volume)
LL, LR, UL = np.array([0.3, -3.0, 0.8]), np.array([-0.3, -3.0, 0.8]), np.array([0.3, -3.0, 1.14])
RIGHT, UP = LR - LL, UL - LL
NORMAL = np.array([0.0, 1.0, 0.0])


def ndc(mvp, point) -> np.ndarray:
    clip = mvp @ np.append(point, 1.0)
    return clip[:3] / clip[3]


def screen_coords(eye, point) -> np.ndarray:
    """Where the ray from the eye through the point meets the screen plane, in the screen's
    own coordinates scaled to -1..1: what the viewer must see the point at."""
    t = ((LL - eye) @ NORMAL) / ((point - eye) @ NORMAL)
    hit = eye + t * (point - eye)
    return np.array([2 * ((hit - LL) @ RIGHT) / (RIGHT @ RIGHT) - 1,
                     2 * ((hit - LL) @ UP) / (UP @ UP) - 1])


def random_eyes(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-1.5, -2.5, 0.3], [1.5, 1.0, 2.0], (n, 3))


def test_screen_corners_are_the_view_corners_from_any_eye():
    for eye in random_eyes(20):
        mvp = ht.off_axis_matrix(eye, LL, LR, UL)
        for corner, want in ((LL, (-1, -1)), (LR, (1, -1)), (UL, (-1, 1)),
                             (LR + UP, (1, 1))):
            np.testing.assert_allclose(ndc(mvp, corner)[:2], want, atol=1e-9)


def test_every_point_is_seen_where_its_ray_crosses_the_screen():
    """On the plane: fixed whoever looks; behind it: follows the eye; in front: against."""
    rng = np.random.default_rng(1)
    eyes = random_eyes(10, seed=2)
    for eye in eyes:
        mvp = ht.off_axis_matrix(eye, LL, LR, UL)
        for _ in range(10):
            on_plane = LL + rng.uniform(0, 1) * RIGHT + rng.uniform(0, 1) * UP
            behind = on_plane - NORMAL * rng.uniform(0.1, 3.0)
            in_front = on_plane + NORMAL * rng.uniform(0.05, 0.3)
            for p in (on_plane, behind, in_front):
                got = ndc(mvp, p)
                np.testing.assert_allclose(got[:2], screen_coords(eye, p), atol=1e-9)
                assert -1 < got[2] < 1  # between the near and far planes
            np.testing.assert_allclose(ndc(mvp, on_plane)[:2],
                                       ndc(ht.off_axis_matrix(eyes[0], LL, LR, UL),
                                           on_plane)[:2], atol=1e-9)
    # moving the eye right (screen +x), a point behind moves right, one in front left
    centre = LL + (RIGHT + UP) / 2
    a = ht.off_axis_matrix(centre + NORMAL - 0.2 * RIGHT, LL, LR, UL)
    b = ht.off_axis_matrix(centre + NORMAL + 0.2 * RIGHT, LL, LR, UL)
    assert ndc(b, centre - NORMAL)[0] > ndc(a, centre - NORMAL)[0]
    assert ndc(b, centre + 0.3 * NORMAL)[0] < ndc(a, centre + 0.3 * NORMAL)[0]


def test_eye_behind_the_screen_is_refused():
    with pytest.raises(ValueError, match="behind the screen"):
        ht.off_axis_matrix(LL - NORMAL, LL, LR, UL)


def test_rendered_views_put_things_where_the_rays_say():
    w, h = 300, 170  # the screen's aspect
    r = ht.ViewRenderer(w, h)
    try:
        centre = LL + (RIGHT + UP) / 2
        on_plane = ht.quad(centre - 0.05 * RIGHT - 0.1 * UP, 0.1 * RIGHT, 0.2 * UP)
        behind_centre = centre - 0.8 * NORMAL
        behind = ht.quad(behind_centre - 0.05 * RIGHT - 0.1 * UP, 0.1 * RIGHT, 0.2 * UP)

        def mask(eye, triangles):
            img = r.render(ht.off_axis_matrix(eye, LL, LR, UL), [(triangles, (1, 1, 1))])
            return img[:, :, 0] > 127

        def pixel(eye, point):
            s = screen_coords(eye, point)
            return np.array([(s[0] + 1) / 2 * w, (1 - s[1]) / 2 * h])  # x right, y down

        eyes = [centre + NORMAL * 1.5, centre + NORMAL * 1.2 + 0.4 * RIGHT - 0.3 * UP]
        full = ht.quad(LL, RIGHT, UP)
        assert mask(eyes[1], full).mean() > 0.995  # the screen fills the view
        np.testing.assert_array_equal(mask(eyes[0], on_plane), mask(eyes[1], on_plane))
        for eye in eyes:
            m = mask(eye, behind)
            ys, xs = np.nonzero(m)
            centroid = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
            np.testing.assert_allclose(centroid, pixel(eye, behind_centre), atol=0.75)
        shift = np.nonzero(mask(eyes[1], behind))[1].mean() - \
            np.nonzero(mask(eyes[0], behind))[1].mean()
        assert shift > 5  # the eye moved right on the screen: the thing behind followed it
    finally:
        r.release()


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


EXAMPLES_ENV = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{ROOT / 'examples'}")


def run_against_sim_daemon(tmp_path, example: str, *args) -> subprocess.CompletedProcess:
    """`mocapd start` on a simulated 4-camera rig sending UDP to a free loopback port, and
    the example run against it (`--port` given); the daemon stopped after."""
    port = _free_udp_port()
    cfg = tmp_path / "mocapd.toml"
    cfg.write_text(f'[sim]\ncameras = 4\nbodies = 2\nfps = 100\n'
                   f'[[udp]]\naddress = "127.0.0.1:{port}"\n')
    daemon = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--config", cfg,
                               "--duration", "60", "--runtime-dir", tmp_path],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              env=EXAMPLES_ENV)
    try:
        return subprocess.run([sys.executable, str(ROOT / "examples" / example),
                               "--port", str(port), *map(str, args)],
                              capture_output=True, text=True, env=EXAMPLES_ENV, timeout=120)
    finally:
        daemon.terminate()
        daemon.communicate(timeout=30)


def test_head_tracking_against_the_simulated_daemon(tmp_path):
    screen = " ".join(",".join(f"{v:g}" for v in p) for p in (LL, LR, UL))
    run = run_against_sim_daemon(tmp_path, "head_tracking.py", "--body", 1, "--screen",
                                 screen, "--frames", 5, "--width", 160, "--timeout", 30,
                                 "--out", tmp_path / "views")
    assert run.returncode == 0, run.stderr
    eyes = np.array([[float(v) for v in line.split("eye")[1].split()]
                     for line in run.stdout.splitlines() if " eye " in line])
    assert len(eyes) == 5 and np.isfinite(eyes).all()
    assert (np.abs(eyes[:, :2]) < 2.5).all()  # the simulated bodies fly in the 4 m volume
    views = sorted((tmp_path / "views").glob("view_*.png"))
    assert len(views) == 5
    import cv2

    img = cv2.imread(str(views[-1]))
    assert img.shape[1] == 160 and (img > 200).any()  # the white frame on the screen plane


def test_head_tracking_refuses_a_bad_screen(tmp_path):
    run = subprocess.run([sys.executable, str(ROOT / "examples" / "head_tracking.py"),
                          "--port", "9", "--body", "1", "--screen", "0,0,0 1,0,0",
                          "--out", tmp_path],
                         capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert run.returncode != 0 and "needs 3 points" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1


def _helix_poses(n=400, fps=100.0):
    """A wand sweeping a helix while turning about z and x: (t_ns, positions, rotations)."""
    from scipy.spatial.transform import Rotation

    t = np.arange(n) / fps
    pos = np.stack([0.5 * np.cos(t), 0.5 * np.sin(t), 1.0 + 0.1 * t], axis=1)
    rot = Rotation.from_euler("zx", np.stack([t, 0.5 * np.sin(2 * t)], axis=1)).as_matrix()
    return (t * 1e9).astype(np.int64), pos, rot


def test_painting_follows_the_tip_and_breaks_strokes_where_the_wand_was_lost():
    tip = np.array([0.02, -0.01, 0.12])
    t_ns, pos, rot = _helix_poses()
    truth_tip = pos + np.einsum("nij,j->ni", rot, tip)
    lost = (np.arange(len(t_ns)) >= 150) & (np.arange(len(t_ns)) < 180)  # 0.3 s unseen
    painting = paint3d.Painting(tip, gap_s=0.1, jump_m=0.1, spacing_m=0.004)
    for i in range(len(t_ns)):
        painting.add(t_ns[i], not lost[i], pos[i], rot[i])
    # a teleport: the body re-acquired 1 m away starts a new stroke, not a line across
    painting.add(t_ns[-1] + 10_000_000, True, pos[-1] + [1.0, 0, 0], rot[-1])
    painting.add(t_ns[-1] + 20_000_000, True, pos[-1] + [1.0, 0, 0.01], rot[-1])
    strokes = painting.points()
    assert len(strokes) == 3
    for stroke, span in zip(strokes[:2], (slice(0, 150), slice(180, None)), strict=True):
        path = truth_tip[span]
        d_to_path = np.linalg.norm(stroke[:, None] - path[None], axis=2).min(axis=1)
        assert d_to_path.max() < 1e-12  # every painted point is the tip at some frame
        d_to_paint = np.linalg.norm(path[:, None] - stroke[None], axis=2).min(axis=1)
        assert d_to_paint.max() < 0.004 + 0.01  # the path covered to the spacing (+1 step)
        assert (np.linalg.norm(np.diff(stroke, axis=0), axis=1) >= 0.004).all()


def test_ply_round_trip(tmp_path):
    strokes = [np.array([[0.0, 0.1, 0.2], [0.3, 0.4, 0.5]]), np.random.default_rng(0)
               .uniform(-2, 2, (7, 3))]
    paint3d.write_ply(tmp_path / "p.ply", strokes)
    v, e = paint3d.read_ply(tmp_path / "p.ply")
    np.testing.assert_allclose(v, np.concatenate(strokes), atol=5e-7)
    np.testing.assert_array_equal(e, [[0, 1]] + [[i, i + 1] for i in range(2, 8)])


def test_paint3d_against_the_simulated_daemon(tmp_path):
    run = run_against_sim_daemon(tmp_path, "paint3d.py", "--body", 1, "--tip", "0,0,0.1",
                                 "--seconds", 3, "--timeout", 30,
                                 "--out", tmp_path / "painting.ply")
    assert run.returncode == 0, run.stderr
    v, e = paint3d.read_ply(tmp_path / "painting.ply")
    assert len(v) > 20 and len(e) >= len(v) // 2
    assert (np.abs(v[:, :2]) < 2.5).all() and (v[:, 2] > -0.5).all()  # in the volume
    step = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    assert step.max() <= 0.1  # no line across the room (the jump limit)


@pytest.mark.parametrize("args, message", [
    (["--tip", "0,0"], "--tip needs x,y,z"),
    (["--out", "x.obj"], "PLY file"),
])
def test_paint3d_refuses_bad_input(tmp_path, args, message):
    base = {"--port": "9", "--body": "1", "--out": str(tmp_path / "p.ply")}
    for k, v in zip(args[::2], args[1::2], strict=True):
        base[k] = v
    run = subprocess.run([sys.executable, str(ROOT / "examples" / "paint3d.py"),
                          *[x for kv in base.items() for x in kv]],
                         capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert run.returncode == 2 and message in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
