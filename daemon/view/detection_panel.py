"""The live view's Detection tab: a camera's threshold, blob sizes and mask, changed on the
page, written to its [[camera]] table and applied by the daemon at once.

Detection happens where the images are: in each camera's capture thread inside the
daemon. So the page never detects anything itself; it edits the configuration
(daemon.view.camera_edit) and asks the daemon to reload, and the thumbnails show the
blobs the new settings give a moment later. Simulated cameras and recordings give blobs,
not images, and have no [[camera]] table: the tab says so instead.
"""

from __future__ import annotations

import numpy as np

from daemon.view import camera_edit, quiet


class DetectionPanel:
    def __init__(self, gui, view) -> None:
        """Build the tab's widgets (inside the tab's context); `view` is the LiveView."""
        self.view = view
        cams = view.desc["cameras"]
        self.names = [c.name for c in view.desc["rig"] if c.name in cams]
        if not self.names:
            gui.add_markdown("No camera of this daemon has a `[[camera]]` table: detection "
                             "settings belong to cameras that give images (simulated cameras "
                             "and recordings give blobs).")
            self.choice = None
            return
        gui.add_markdown("Pick a camera, change how it detects markers and press **Apply "
                         "and save**: the setting goes into its `[[camera]]` table (the rest "
                         "of the file is kept) and the daemon applies it between two frames.")
        self.choice = gui.add_dropdown("Camera", self.names, initial_value=self.names[0])
        self.threshold = gui.add_text("Threshold", "")
        self.min_area = gui.add_number("Min area (px)", 2.0, min=0.0, step=0.5)
        self.max_area = gui.add_number("Max area (px)", 4000.0, min=1.0, step=1.0)
        apply = gui.add_button("Apply and save", color="green")
        gui.add_markdown("**Mask**: take the markers out of the camera's view first; what it "
                         "still sees (lamps, reflections, other cameras' LEDs) is masked.")
        mask_now = gui.add_button("Mask the blobs seen now")
        clear = gui.add_button("Clear mask", color="red")
        self.message = gui.add_markdown("")
        self.choice.on_update(lambda _: self.fill())
        apply.on_click(lambda _: view.run_edit(self._apply, self.message))
        mask_now.on_click(lambda _: view.run_edit(self._mask_now, self.message))
        clear.on_click(lambda _: view.run_edit(self._clear, self.message))
        self.fill()

    def fill(self) -> None:
        """The chosen camera's settings as the daemon runs them."""
        if self.choice is None:
            return
        c = self.view.desc["cameras"].get(self.choice.value)
        if c is None:
            return
        self.threshold.value = str(c["threshold"])
        self.min_area.value = float(c["min_area"])
        self.max_area.value = float(c["max_area"])

    def _camera(self) -> str:
        """The chosen camera, one of the tab's (a crafted message can send any name, and
        the name makes the mask's file name)."""
        return quiet.choice(self.choice.value, self.names, "camera")

    def _apply(self) -> str:
        name = self._camera()
        now = self.view.desc["cameras"][name]
        thr = camera_edit.parse_threshold(quiet.text(self.threshold.value, "threshold", 20))
        lo = quiet.number(self.min_area.value, "min area", 0.0, 1e7)
        hi = quiet.number(self.max_area.value, "max area", 0.0, 1e7)
        if lo >= hi:
            raise camera_edit.UserError(f"min area ({lo:g}) must be below max area ({hi:g})")
        # only what changed is written: a file keeps its defaults unwritten
        camera_edit.set_detection(
            self.view.desc["config"], name,
            threshold=thr if thr != now["threshold"] else None,
            min_area=lo if lo != now["min_area"] else None,
            max_area=hi if hi != now["max_area"] else None)
        return f"{name}: threshold {thr}, blob area {lo:g} to {hi:g} px saved"

    def _mask_now(self) -> str:
        name = self._camera()
        rig = self.view.desc["rig"]
        c = rig.names.index(name)
        uv, area = self.view.blobs.get(c, (np.zeros((0, 2)), np.zeros(0)))
        if not len(uv):
            return f"{name} sees no blobs: nothing to mask"
        mask = camera_edit.mask_from_blobs(rig[name].size, uv, area)
        path = camera_edit.set_mask(self.view.desc["config"], name, mask)
        return f"{name}: {len(uv)} blobs masked ({path.name})"

    def _clear(self) -> str:
        name = self._camera()
        camera_edit.set_mask(self.view.desc["config"], name, None)
        return f"{name}: mask cleared"
