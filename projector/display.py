"""Drawing calibration dots with moderngl: a full-screen window, or off-screen through EGL.

Both targets share one renderer, so the simulator's camera sees the very image a real
monitor or projector would show. A dot is an anti-aliased white disc on black at a sub-pixel
position: each pixel's value is the disc's coverage of the pixel's area, estimated on an
8 x 8 grid of sub-samples, each with a linear edge ramp one sub-sample wide. Coverage (not a
point sample) is what keeps the dot's intensity centroid on the requested centre, to a few
thousandths of a pixel, for any sub-pixel offset. Pixel centres sit at integer coordinates,
row 0 at the top, as in images.
"""

from __future__ import annotations

import numpy as np

from calibkit.core.errors import UserError
from projector.dots import Dots
from projector.screens import require_display

_VERTEX = """
#version 330
in vec2 corner;          // unit quad corner in [-1, 1]
in vec3 dot;             // x, y (pixels, y down), radius (pixels)
in float level;          // brightness 0..1
uniform vec2 screen;     // width, height in pixels
out vec2 centre;
out float radius;
out float bright;
void main() {
    float reach = dot.z + 1.5;
    vec2 p = dot.xy + corner * reach;         // pixel coordinates, centres at integers
    vec2 ndc = vec2((p.x + 0.5) / screen.x * 2.0 - 1.0, 1.0 - (p.y + 0.5) / screen.y * 2.0);
    gl_Position = vec4(ndc, 0.0, 1.0);
    centre = dot.xy;
    radius = dot.z;
    bright = level;
}
"""

_FRAGMENT = """
#version 330
in vec2 centre;
in float radius;
in float bright;
uniform vec2 screen;
out vec4 colour;
const int S = 8;
void main() {
    // this fragment's pixel centre in image coordinates (row 0 at the top)
    vec2 pix = vec2(gl_FragCoord.x - 0.5, screen.y - gl_FragCoord.y - 0.5);
    vec2 d0 = pix - centre;
    float cover = 0.0;
    for (int i = 0; i < S; ++i) {
        for (int j = 0; j < S; ++j) {
            vec2 o = d0 + (vec2(float(i), float(j)) + 0.5) / float(S) - 0.5;
            cover += clamp((radius - length(o)) * float(S) + 0.5, 0.0, 1.0);
        }
    }
    cover /= float(S * S);
    if (cover <= 0.0) discard;
    colour = vec4(vec3(cover * bright), 1.0);
}
"""


class _Renderer:
    """The shader program and instanced quad, bound to one moderngl context."""

    def __init__(self, ctx, size: tuple[int, int]) -> None:
        self.ctx = ctx
        self.size = (int(size[0]), int(size[1]))
        self.prog = ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        self.prog["screen"].value = (float(self.size[0]), float(self.size[1]))
        quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4")
        self.quad = ctx.buffer(quad.tobytes())
        self.capacity = 0
        self.inst = None
        self.vao = None

    def _ensure(self, n: int) -> None:
        if n <= self.capacity:
            return
        self.capacity = max(n, 2 * self.capacity, 256)
        if self.inst is not None:
            self.inst.release()
            self.vao.release()
        self.inst = self.ctx.buffer(reserve=self.capacity * 16)
        self.vao = self.ctx.vertex_array(self.prog, [
            (self.quad, "2f", "corner"),
            (self.inst, "3f 1f/i", "dot", "level"),
        ])

    def draw(self, dots: Dots) -> None:
        self.ctx.clear(0.0, 0.0, 0.0, 1.0)
        n = len(dots.xy)
        if n == 0:
            return
        self._ensure(n)
        data = np.column_stack([dots.xy, dots.radius_px, dots.level]).astype("f4")
        self.inst.write(data.tobytes())
        self.vao.render(mode=self.ctx.TRIANGLE_STRIP, vertices=4, instances=n)


class OffscreenDisplay:
    """The renderer through headless EGL: `render(dots)` returns the frame as numpy.

    float32 frames (0..1) keep the exact coverage for the simulator; `render_u8` gives what
    an 8-bit monitor would show.
    """

    def __init__(self, size: tuple[int, int]) -> None:
        # deferred on purpose: loads moderngl only where used
        import moderngl

        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # no EGL driver: a setup problem the user can fix
            raise UserError(f"cannot create a headless OpenGL (EGL) context: {exc}") from None
        self.size = (int(size[0]), int(size[1]))
        self.fbo = self.ctx.simple_framebuffer(self.size, components=1, dtype="f4")
        self.fbo.use()
        self.renderer = _Renderer(self.ctx, self.size)
        self.refresh_hz = 60.0
        self.shown = np.zeros((self.size[1], self.size[0]), np.float32)  # what is on the glass
        self._watchers: list = []

    def watch(self, callback) -> None:
        """Call `callback(frame)` with every frame `show` puts on the glass: a simulated
        camera watching this monitor gets exactly the picture a window would draw."""
        self._watchers.append(callback)

    def show(self, dots: Dots) -> None:
        """Draw `dots` as `WindowDisplay.show` does (the same renderer), off-screen: the
        frame stays in `shown` and goes to every watcher, so a capture can be handed this
        display in place of a window (`calibkit intrinsic --display --sim`)."""
        self.shown = self.render(dots)
        for callback in self._watchers:
            callback(self.shown)

    def render(self, dots: Dots) -> np.ndarray:
        """The frame (h, w) float32 in 0..1, row 0 at the top."""
        self.fbo.use()
        self.renderer.draw(dots)
        w, h = self.size
        data = np.frombuffer(self.fbo.read(components=1, dtype="f4"), dtype=np.float32)
        return data.reshape(h, w)[::-1].copy()

    def render_u8(self, dots: Dots) -> np.ndarray:
        return np.clip(np.rint(self.render(dots) * 255.0), 0, 255).astype(np.uint8)

    def close(self) -> None:
        self.ctx.release()

    def __enter__(self) -> OffscreenDisplay:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class WindowDisplay:
    """A full-screen, borderless, vsynced window on one monitor (or projector), via glfw.

    `show(dots)` draws and swaps; with vsync the frame is on the glass one refresh later.
    Needs the `glfw` package and a running display server.
    """

    def __init__(self, monitor_index: int = 0) -> None:
        require_display()
        try:
            # deferred on purpose: loads glfw only where used
            import glfw
        except ModuleNotFoundError:
            raise UserError("showing patterns on a monitor needs the 'glfw' package: "
                            "pip install glfw") from None
        # deferred on purpose: loads moderngl only where used
        import moderngl

        if not glfw.init():
            raise UserError("glfw could not start: is a display server running?")
        monitors = glfw.get_monitors()
        if not 0 <= monitor_index < len(monitors):
            glfw.terminate()
            raise UserError(f"no monitor {monitor_index}: found {len(monitors)} "
                            "(see `calibkit displays`)")
        monitor = monitors[monitor_index]
        mode = glfw.get_video_mode(monitor)
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.DECORATED, glfw.FALSE)
        glfw.window_hint(glfw.REFRESH_RATE, mode.refresh_rate)
        self.window = glfw.create_window(mode.size.width, mode.size.height, "calibkit",
                                         monitor, None)
        if not self.window:
            glfw.terminate()
            raise UserError("could not open a full-screen window on that monitor")
        glfw.make_context_current(self.window)
        glfw.swap_interval(1)  # vsync
        self._glfw = glfw
        self.size = (mode.size.width, mode.size.height)
        self.refresh_hz = float(mode.refresh_rate)
        self.ctx = moderngl.create_context()
        self.renderer = _Renderer(self.ctx, self.size)

    def show(self, dots: Dots) -> None:
        self.ctx.screen.use()
        self.renderer.draw(dots)
        self._glfw.swap_buffers(self.window)
        self._glfw.poll_events()

    def close(self) -> None:
        self._glfw.destroy_window(self.window)
        self._glfw.terminate()

    def __enter__(self) -> WindowDisplay:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

