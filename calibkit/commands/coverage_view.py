"""A web page of a wand capture's coverage filling in (`calibkit wand --view [HOST:]PORT`).

While the wand is waved, each camera's image grid (the capture monitor's cells, the same
that decide when a camera has enough) is drawn as it fills: visited cells green, the rest
dark, with the camera's wand sightings and coverage against the targets. The user sees
where in which camera to wave next without reading the terminal. The page runs in the
calibration's process (viser's server thread) and is redrawn at most REDRAW_HZ times a
second from the monitor's arrays, a few small images: a capture is not slowed by it.
"""

from __future__ import annotations

import contextlib
import io
import time

import cv2
import numpy as np

from calibkit.core.errors import UserError

REDRAW_HZ = 4.0
THUMB_WIDTH_PX = 240
VISITED = (60, 190, 90)
EMPTY = (35, 35, 40)


def coverage_image(cells: np.ndarray, size: tuple[int, int], done: bool,
                   width_px: int = THUMB_WIDTH_PX) -> np.ndarray:
    """(h, w, 3) RGB: the camera's grid cells (bool (gy, gx), True: the wand went there) at
    the camera's aspect, visited cells green, grid lines between; a green frame when the
    camera has enough."""
    gy, gx = cells.shape
    w, h = size
    th = max(1, round(h * width_px / w))
    img = np.empty((th, width_px, 3), np.uint8)
    ys = np.minimum((np.arange(th) * gy) // th, gy - 1)
    xs = np.minimum((np.arange(width_px) * gx) // width_px, gx - 1)
    img[:] = np.where(cells[ys][:, xs][..., None], np.array(VISITED, np.uint8),
                      np.array(EMPTY, np.uint8))
    for k in range(1, gx):
        img[:, (k * width_px) // gx] = 80
    for k in range(1, gy):
        img[(k * th) // gy, :] = 80
    if done:
        cv2.rectangle(img, (0, 0), (width_px - 1, th - 1), (120, 255, 120), 3)
    return img



def open_page(host: str, port: int, label: str):
    """A viser server on host:port with the pages' theme; a port in use is the user's to
    change (one line)."""
    # deferred on purpose: loads viser only where used
    import viser

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    # the page is served only where the user said, never through viser's share tunnel
    server.request_share_url = lambda *args, **kwargs: None
    if server.get_port() != port:
        server.stop()
        raise UserError(f"--view: port {port} on {host} is taken; choose another")
    server.gui.configure_theme(control_width="large", dark_mode=True, show_logo=False,
                               show_share_button=False)
    return server

class CoverageView:
    """The page; `update(monitor)` after each batch of frames (it redraws when due)."""

    def __init__(self, host: str, port: int, monitor) -> None:
        self.server = open_page(host, port, "calibkit wand")
        gui = self.server.gui
        self.head = gui.add_markdown("**wand capture**: waiting for the first frames")
        self.images, self.text = [], []
        for name, size, cells in zip(monitor.names, monitor.sizes, monitor.cells,
                                     strict=True):
            wh = (int(size[0]), int(size[1]))
            self.images.append(gui.add_image(coverage_image(cells, wh, False), label=name,
                                             format="png"))
            self.text.append(gui.add_markdown(f"`{name}`: 0 sightings, 0 % covered"))
        self._next = 0.0
        self.redraws = 0
        self.url = f"http://{host if ':' not in host else f'[{host}]'}:{port}"

    def update(self, monitor, frames: int, final: bool = False) -> None:
        now = time.monotonic()
        if now < self._next and not final:
            return
        self._next = now + 1.0 / REDRAW_HZ
        done = monitor.camera_done()
        cov = monitor.coverage
        with self.server.atomic():
            for c, name in enumerate(monitor.names):
                wh = (int(monitor.sizes[c, 0]), int(monitor.sizes[c, 1]))
                self.images[c].image = coverage_image(monitor.cells[c], wh, bool(done[c]))
                self.text[c].content = (
                    f"`{name}`: {int(monitor.samples[c])} sightings of "
                    f"{monitor.min_samples}, {100 * cov[c]:.0f} % covered of "
                    f"{100 * monitor.min_coverage:.0f} %" + (", **enough**" if done[c] else ""))
            state = "captured" if final else "capturing"
            self.head.content = (f"**wand capture** ({state}): {frames} frames, "
                                 f"{int(done.sum())} of {len(done)} cameras have enough")
        self.redraws += 1

    def close(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # its "server stopped" line
            self.server.stop()


class ViewProgress:
    """Progress that also redraws the page: what the capture loop calls per batch."""

    def __init__(self, progress, view: CoverageView, monitor) -> None:
        self.progress, self.view, self.monitor = progress, view, monitor

    @property
    def done(self) -> int:
        return self.progress.done

    def update(self, frames: int, text: str = "") -> None:
        self.progress.update(frames, text)
        self.view.update(self.monitor, frames)

    def finish(self, text: str = "") -> None:
        self.progress.finish(text)
        self.view.update(self.monitor, self.progress.done, final=True)


def dots_image(size: tuple[int, int], views: list, width_px: int = THUMB_WIDTH_PX
               ) -> np.ndarray:
    """(h, w, 3) RGB: the decoded dots of `views` over the camera's image (the last view
    bright, the ones before dim), on the 8 x 6 cells the coverage figure counts, those
    holding a dot tinted green."""
    w, h = size
    s = width_px / w
    th = max(1, round(h * s))
    uv = np.concatenate([v.uv for v in views]) if views else np.zeros((0, 2))
    cells = np.zeros((6, 8), bool)
    if len(uv):
        ix = np.clip((uv[:, 0] / w * 8).astype(int), 0, 7)
        iy = np.clip((uv[:, 1] / h * 6).astype(int), 0, 5)
        cells[iy, ix] = True
    img = coverage_image(cells, size, False, width_px)
    img[np.all(img == np.array(VISITED, np.uint8), axis=2)] = (30, 80, 45)
    for k, v in enumerate(views):
        colour = (255, 255, 255) if k == len(views) - 1 else (150, 150, 150)
        for x, y in np.round(np.asarray(v.uv) * s).astype(int).tolist():
            if 0 <= x < width_px and 0 <= y < th:
                img[y, x] = colour
    return img


class IntrinsicView:
    """`calibkit intrinsic --view`: per camera, the views taken so far (their decoded dots
    over the image, the cells they cover) and what to do next; `show(name, size, views,
    wanted)` after each view (live) or each camera (simulated)."""

    def __init__(self, host: str, port: int) -> None:
        self.server = open_page(host, port, "calibkit intrinsic")
        gui = self.server.gui
        gui.add_markdown("**intrinsic calibration**: each camera's views as they are taken; "
                         "the monitor's dots each view decoded (the newest bright), the image "
                         "cells they reached (green)")
        self.cameras: dict[str, tuple] = {}
        self.url = f"http://{host if ':' not in host else f'[{host}]'}:{port}"

    def show(self, name: str, size: tuple[int, int], views: list, wanted: int) -> None:
        from calibkit.calibrate.intrinsic import coverage, guidance

        gui = self.server.gui
        if name not in self.cameras:
            img = gui.add_image(dots_image(size, []), label=name, format="png")
            self.cameras[name] = (img, gui.add_markdown(f"`{name}`: no view yet"))
        img, text = self.cameras[name]
        uv = np.concatenate([v.uv for v in views]) if views else np.zeros((0, 2))
        per_view = ", ".join(str(len(v.uv)) for v in views) or "-"
        with self.server.atomic():
            img.image = dots_image(size, views)
            text.content = (f"`{name}`: {len(views)} of {wanted} views, dots per view "
                            f"{per_view}; image coverage {100 * coverage(uv, size):.0f} %"
                            + (f"  \nnext: {guidance(views, size, wanted)}"
                               if len(views) < wanted else ""))

    def close(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
