"""GenICam cameras through harvesters (`genicam:SERIAL`), with the camera's own time and id.

Any camera whose maker ships a GenTL producer (a .cti file: FLIR/Teledyne, Allied Vision,
IDS, Hikrobot, Daheng...) is reached this way. Written to harvesters' documented API
(1.4) and not run against a camera here (there is none on the build machine, and
harvesters is not a dependency: `pip install harvesters`). What is tested is what does not
need the camera: the stamps and image taken from a buffer, the producer lookup and the
errors when harvesters or a producer is missing.

The producer file is MOCAPD_GENTL_CTI if set, else the first .cti in the directories of
GENICAM_GENTL64_PATH (the GenTL standard's variable, set by most makers' installers).
Each frame carries the camera's timestamp and frame id as harvesters documents them:
Buffer.timestamp with Buffer.timestamp_frequency ticks per second (harvesters gives ns and
1 GHz where the producer converts, the raw ticks and the device's tick rate otherwise) and
the GenTL buffer's frame id (BUFFER_INFO_FRAMEID, on Buffer.module).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from calibkit.cameras.base import Capabilities, Frame, FrameSource, Warn, rate_differs
from calibkit.core.errors import UserError

LIBRARY = "harvesters"
CTI_VARIABLE = "MOCAPD_GENTL_CTI"


def _harvester_class():
    """harvesters' Harvester, or a one-line error saying how to get it."""
    try:
        from harvesters.core import Harvester
    except ImportError:
        raise UserError("genicam: cameras need harvesters, which is not installed "
                        "(pip install harvesters)") from None
    return Harvester


def producer_file(environ: Mapping[str, str] = os.environ) -> str:
    """The GenTL producer (.cti) to load: MOCAPD_GENTL_CTI, else the first .cti file (in
    name order) of the GENICAM_GENTL64_PATH directories."""
    cti = environ.get(CTI_VARIABLE)
    if cti:
        if not Path(cti).is_file():
            raise UserError(f"{CTI_VARIABLE}={cti}: no such file")
        return cti
    for folder in environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if folder and Path(folder).is_dir():
            found = sorted(Path(folder).glob("*.cti"))
            if found:
                return str(found[0])
    raise UserError(f"genicam: cameras need a GenTL producer (the .cti file from the "
                    f"camera maker's SDK): set {CTI_VARIABLE} to its path")


def stamps(buf) -> tuple[int, int]:
    """(device time ns, frame id) of a harvesters Buffer; -1 for what it lacks."""
    try:
        ticks, hz = int(buf.timestamp), int(buf.timestamp_frequency)
    except Exception:  # noqa: BLE001 - the producer gives no timestamp at all
        ticks, hz = 0, 0
    device_ns = ticks * 1_000_000_000 // hz if ticks > 0 and hz > 0 else -1
    try:
        frame_id = int(buf.module.frame_id)  # the GenTL buffer's BUFFER_INFO_FRAMEID
    except Exception:  # noqa: BLE001 - not every producer reports it
        frame_id = -1
    return device_ns, frame_id


def image_of(component) -> np.ndarray:
    """A copy of a 2D image component as the detector takes it: (h, w) for mono and raw
    Bayer formats, (h, w, 3) BGR for RGB/BGR ones."""
    n = int(round(float(getattr(component, "num_components_per_pixel", 1) or 1)))
    h, w = int(component.height), int(component.width)
    data = np.asarray(component.data)
    image = data.reshape(h, w) if n == 1 else data.reshape(h, w, n)[:, :, :3]
    if n >= 3 and str(getattr(component, "data_format", "")).upper().startswith("RGB"):
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image).copy()


def _set(node_map, names: tuple[str, ...], value) -> bool:
    """Set the first of these features the camera has. False: none could be set."""
    for name in names:
        try:
            getattr(node_map, name).value = value
            return True
        except Exception:  # noqa: BLE001 - a model without the feature, or read-only now
            continue
    return False


def _get(node_map, names: tuple[str, ...]):
    for name in names:
        try:
            return getattr(node_map, name).value
        except Exception:  # noqa: BLE001
            continue
    return None


class GenICamSource(FrameSource):
    """A GenICam camera (the first one the producer finds when no serial is given)."""

    capabilities = Capabilities(live=True, device_timestamps=True, device_frame_ids=True,
                                set_fps=True, set_exposure=True)

    def __init__(self, serial: str = "", fps: float | None = None,
                 exposure_us: float | None = None, camera: str | None = None,
                 warn: Warn | None = None) -> None:
        harvester = _harvester_class()
        cti = producer_file()
        self.serial = serial
        self.camera = camera or (f"genicam{serial}" if serial else "genicam")
        self.h = harvester()
        try:
            self.h.add_file(cti)
            self.h.update()
            try:
                self.ia = self.h.create({"serial_number": serial} if serial else None)
            except (ValueError, IndexError):
                have = ", ".join(str(getattr(d, "serial_number", "?"))
                                 for d in self.h.device_info_list) or "none"
                raise UserError(f"no GenICam camera {serial} found through {cti} "
                                f"(connected: {have})") from None
            try:
                self._configure(fps, exposure_us, warn)
                self.ia.start()
            except BaseException:
                self.ia.destroy()
                raise
        except BaseException:
            self.h.reset()
            raise

    def _configure(self, fps: float | None, exposure_us: float | None,
                   warn: Warn | None) -> None:
        nodes = self.ia.remote_device.node_map
        if exposure_us is not None:
            _set(nodes, ("ExposureAuto",), "Off")
            if not _set(nodes, ("ExposureTime", "ExposureTimeAbs"), float(exposure_us)):
                raise UserError(f"GenICam camera {self.camera}: the exposure time could "
                                f"not be set to {exposure_us:g} us")
        if fps is not None:
            _set(nodes, ("AcquisitionFrameRateEnable", "AcquisitionFrameRateEnabled"), True)
            if not _set(nodes, ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"),
                        float(fps)):
                raise UserError(f"GenICam camera {self.camera}: the frame rate could not "
                                f"be set to {fps:g} fps")
        got = _get(nodes, ("ResultingFrameRate", "AcquisitionFrameRate"))
        self.fps = float(got) if got else None
        if fps is not None and warn is not None and got is not None and rate_differs(fps, got):
            warn(f"GenICam camera {self.camera}: asked for {fps:g} fps, it runs at "
                 f"{float(got):g} fps")

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        while True:
            with self.ia.fetch(timeout=2.0) as buf:
                arrival = time.monotonic_ns()
                device_ns, frame_id = stamps(buf)
                image = image_of(buf.payload.components[0])
            yield Frame(self.camera, i, arrival, image, device_ns, frame_id)
            i += 1

    def close(self) -> None:
        try:
            self.ia.stop()
            self.ia.destroy()
        finally:
            self.h.reset()
