"""Off-axis head tracking: a monitor becomes a window into a 3D scene for a tracked viewer.

A rigid body worn on the head (glasses, a cap) gives the eye's position; the picture on the
screen is the view through the screen rectangle from that eye: an asymmetric frustum whose
apex is the eye and whose edges pass through the screen's corners (the generalised
perspective projection). Points on the screen plane stay where they are whoever looks;
things behind it follow the eye, things in front move against it, which is the depth cue.

    python examples/head_tracking.py --port 9870 --body 1 \
        --screen "-0.3,1.5,0.8 0.3,1.5,0.8 -0.3,1.5,1.14" --frames 100 --out views/

`--screen`: the screen's lower-left, lower-right and upper-left corners in the mocap world
(metres; measure them with a tracked wand tip, or from the monitor's size and pose).
`--eye-offset`: the eye midpoint in the head body's frame. Rendering is headless (EGL), so
this runs anywhere; each view is written as a PNG (on a real display the same matrix goes to
the window's draw call).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

_VERTEX = """
#version 330
uniform mat4 mvp;
in vec3 in_pos;
void main() { gl_Position = mvp * vec4(in_pos, 1.0); }
"""
_FRAGMENT = """
#version 330
uniform vec3 colour;
out vec4 frag;
void main() { frag = vec4(colour, 1.0); }
"""


def frustum(left: float, right: float, bottom: float, top: float, near: float,
            far: float) -> np.ndarray:
    """OpenGL's perspective matrix for a frustum given at the near plane."""
    return np.array([
        [2 * near / (right - left), 0, (right + left) / (right - left), 0],
        [0, 2 * near / (top - bottom), (top + bottom) / (top - bottom), 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0]])


def off_axis_matrix(eye, lower_left, lower_right, upper_left, near: float = 0.05,
                    far: float = 50.0) -> np.ndarray:
    """World -> clip matrix of the view through the screen rectangle from `eye`: the
    screen's corners land on the clip rectangle's corners for any eye in front of it."""
    pa, pb, pc, pe = (np.asarray(v, float) for v in (lower_left, lower_right, upper_left, eye))
    right = (pb - pa) / np.linalg.norm(pb - pa)
    up = (pc - pa) / np.linalg.norm(pc - pa)
    normal = np.cross(right, up)
    normal /= np.linalg.norm(normal)
    va, vb, vc = pa - pe, pb - pe, pc - pe
    distance = -va @ normal
    if distance <= 0:
        raise ValueError("the eye is behind the screen (or in its plane)")
    scale = near / distance
    projection = frustum(right @ va * scale, right @ vb * scale, up @ va * scale,
                         up @ vc * scale, near, far)
    rotate = np.eye(4)
    rotate[:3, :3] = np.stack([right, up, normal])
    translate = np.eye(4)
    translate[:3, 3] = -pe
    return projection @ rotate @ translate


def quad(corner, u, v) -> np.ndarray:
    """Two triangles of the parallelogram corner, corner+u, corner+v: (2, 3, 3)."""
    c, u, v = (np.asarray(x, float) for x in (corner, u, v))
    return np.array([[c, c + u, c + u + v], [c, c + u + v, c + v]])


def box(centre, size: float) -> np.ndarray:
    """The 12 triangles of an axis-aligned cube."""
    c, h = np.asarray(centre, float), size / 2
    e = np.eye(3) * size
    faces = []
    for axis in range(3):
        u, v = e[(axis + 1) % 3], e[(axis + 2) % 3]
        for sign in (-1, 1):
            corner = c - h + (e[axis] if sign > 0 else 0)
            faces.append(quad(corner, u, v))
    return np.concatenate(faces)


def demo_scene(lower_left, lower_right, upper_left) -> list[tuple[np.ndarray, tuple]]:
    """A frame on the screen plane, cubes behind it at several depths and one in front."""
    pa, pb, pc = (np.asarray(v, float) for v in (lower_left, lower_right, upper_left))
    right, up = pb - pa, pc - pa
    normal = np.cross(right, up)
    normal /= np.linalg.norm(normal)
    centre = pa + (right + up) / 2
    w = 0.04 * min(np.linalg.norm(right), np.linalg.norm(up))
    ur, uu = right / np.linalg.norm(right), up / np.linalg.norm(up)
    border = np.concatenate([quad(pa, right, uu * w), quad(pc - uu * w, right, uu * w),
                             quad(pa, ur * w, up), quad(pb - ur * w, ur * w, up)])
    scene = [(border, (0.9, 0.9, 0.9))]
    size = 0.15 * np.linalg.norm(right)
    for depth, colour in ((0.3, (0.9, 0.3, 0.2)), (0.8, (0.2, 0.7, 0.3)),
                          (1.6, (0.2, 0.4, 0.9))):
        offset = (depth - 0.5) * 0.4 * right
        scene.append((box(centre - normal * depth + offset, size), colour))
    scene.append((box(centre + normal * 0.1 - 0.25 * right, size * 0.5), (0.95, 0.8, 0.2)))
    return scene


class ViewRenderer:
    """Draws a scene through an off-axis matrix into an off-screen image (EGL, no display)."""

    def __init__(self, width: int, height: int) -> None:
        import moderngl

        self.ctx = moderngl.create_standalone_context(backend="egl")
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.program = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        self.fbo = self.ctx.simple_framebuffer((width, height), components=3)
        self.size = (width, height)

    def render(self, mvp: np.ndarray, scene) -> np.ndarray:
        """(height, width, 3) uint8, top row first."""
        self.fbo.use()
        self.fbo.clear(0.05, 0.05, 0.08, depth=1.0)
        self.program["mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        for triangles, colour in scene:
            buf = self.ctx.buffer(np.ascontiguousarray(triangles, dtype="f4").tobytes())
            vao = self.ctx.vertex_array(self.program, [(buf, "3f", "in_pos")])
            self.program["colour"].value = tuple(colour)
            vao.render()
            vao.release()
            buf.release()
        w, h = self.size
        image = np.frombuffer(self.fbo.read(components=3), np.uint8).reshape(h, w, 3)
        return image[::-1].copy()

    def release(self) -> None:
        self.fbo.release()
        self.program.release()
        self.ctx.release()


def parse_points(text: str, count: int, what: str) -> np.ndarray:
    try:
        pts = np.array([[float(v) for v in p.split(",")] for p in text.split()])
    except ValueError:
        raise SystemExit(f"head_tracking: {what} must be numbers, got {text!r}") from None
    if pts.shape != (count, 3):
        raise SystemExit(f"head_tracking: {what} needs {count} points x,y,z, got {text!r}")
    return pts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, required=True, help="mocapd's [[udp]] port")
    ap.add_argument("--body", type=int, required=True, help="the head's rigid-body id")
    ap.add_argument("--screen", required=True,
                    help='lower-left, lower-right, upper-left corners: "x,y,z x,y,z x,y,z"')
    ap.add_argument("--eye-offset", default="0,0,0", help="eye midpoint in the head's frame")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--out", type=Path, required=True, help="folder for the views (PNG)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--timeout", type=float, default=5.0)
    args = ap.parse_args(argv)

    import cv2
    from mocap_udp import PoseReceiver

    screen = parse_points(args.screen, 3, "--screen")
    offset = parse_points(args.eye_offset, 1, "--eye-offset")[0]
    w = args.width
    aspect = np.linalg.norm(screen[2] - screen[0]) / np.linalg.norm(screen[1] - screen[0])
    renderer = ViewRenderer(w, max(1, round(w * aspect)))
    scene = demo_scene(*screen)
    rx = PoseReceiver(args.port)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        for i in range(args.frames):
            try:
                position, rotation = rx.latest(args.body, args.timeout)
            except TimeoutError as exc:
                print(f"head_tracking: {exc}", file=sys.stderr)
                return 1
            eye = position + rotation @ offset
            try:
                mvp = off_axis_matrix(eye, *screen)
            except ValueError as exc:
                print(f"head_tracking: frame {rx.frame}: {exc}; skipped", file=sys.stderr)
                continue
            view = renderer.render(mvp, scene)
            cv2.imwrite(str(args.out / f"view_{i:05d}.png"), view[:, :, ::-1])
            print(f"frame {rx.frame} eye {eye[0]:+.3f} {eye[1]:+.3f} {eye[2]:+.3f}")
    finally:
        rx.close()
        renderer.release()
    return 0


if __name__ == "__main__":
    sys.exit(main())
