"""Basler cameras through pypylon (`basler:SERIAL`), with the camera's own time and counter.

Written to pylon's documented API and not run against a camera here (there is none on the
build machine, and pypylon is not a dependency: `pip install pypylon` brings it, with
Basler's runtime). What is tested is what does not need the camera: the stamps taken from
a grab result, the block-id unwrapping and the error when pypylon is missing.

Each frame carries the camera's timestamp and frame counter as pylon documents them: the
grab result's TimeStamp is the camera's tick count when the frame was taken (ticks since it
powered up or was reset; 1 ns on USB3 cameras, GevTimestampTickFrequency per second on
GigE ones) and BlockID its frame counter (USB3: from 0; GigE: from 1, wrapping after 65535
unless extended ids are on, 0 when unsupported; 2^64 - 1 when the transport has none).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from calibkit.cameras.base import Capabilities, Frame, FrameSource, Warn, rate_differs
from calibkit.core.errors import UserError

LIBRARY = "pypylon"
NO_BLOCK_ID = 2**64 - 1


def _pylon():
    """pypylon's pylon module, or a one-line error saying how to get it."""
    try:
        from pypylon import pylon
    except ImportError:
        raise UserError("basler: cameras need pypylon, which is not installed "
                        "(pip install pypylon)") from None
    return pylon


class BlockIds:
    """A grab result's BlockID as a counter that never wraps (-1: the camera gives none).
    GigE cameras count 1..65535 and start again at 1 (0 means no id); USB3 ones count from
    0 on 64 bits."""

    def __init__(self, gige: bool) -> None:
        self.gige = gige
        self.last = -1
        self.wraps = 0

    def __call__(self, block: int) -> int:
        if block >= NO_BLOCK_ID or (self.gige and block == 0):
            return -1
        if self.gige and 0 <= block < self.last - 32768:
            self.wraps += 1  # 16-bit GigE block ids go 65535 -> 1
        self.last = block
        return block + 65535 * self.wraps


def stamps(result, tick_hz: int, block_ids: BlockIds) -> tuple[int, int]:
    """(device time ns, frame id) of a pylon grab result; -1 for what it lacks."""
    ticks = int(result.TimeStamp)
    device_ns = ticks * 1_000_000_000 // tick_hz if ticks > 0 else -1
    return device_ns, block_ids(int(result.BlockID))


def _set(cam, names: tuple[str, ...], value) -> bool:
    """Set the first of these feature nodes the camera has (USB3 and GigE models name some
    features differently: ExposureTime / ExposureTimeAbs). False: none could be set."""
    for name in names:
        try:
            getattr(cam, name).SetValue(value)
            return True
        except Exception:  # noqa: BLE001 - a model without the node, or not writable now
            continue
    return False


def _get(cam, names: tuple[str, ...]):
    for name in names:
        try:
            return getattr(cam, name).GetValue()
        except Exception:  # noqa: BLE001 - a model without the node
            continue
    return None


class BaslerSource(FrameSource):
    """A Basler camera (the first one found when no serial number is given), grabbing the
    latest image only: a slow reader skips frames rather than falling behind."""

    capabilities = Capabilities(live=True, device_timestamps=True, device_frame_ids=True,
                                set_fps=True, set_exposure=True)

    def __init__(self, serial: str = "", fps: float | None = None,
                 exposure_us: float | None = None, camera: str | None = None,
                 warn: Warn | None = None) -> None:
        pylon = _pylon()
        self.pylon = pylon
        factory = pylon.TlFactory.GetInstance()
        found = list(factory.EnumerateDevices())
        devices = [d for d in found if not serial or str(d.GetSerialNumber()) == serial]
        if not devices:
            have = ", ".join(str(d.GetSerialNumber()) for d in found) or "none"
            raise UserError(f"no Basler camera {serial or ''} found (connected: {have})")
        info = devices[0]
        self.serial = str(info.GetSerialNumber())
        self.camera = camera or self.serial
        self.gige = "GigE" in str(info.GetDeviceClass())
        self.cam = pylon.InstantCamera(factory.CreateDevice(info))
        self.cam.Open()
        try:
            self._configure(fps, exposure_us, warn)
            self.cam.StartGrabbing(pylon.GrabStrategy_LatestImageOnly)
        except BaseException:
            self.cam.Close()
            raise

    def _configure(self, fps: float | None, exposure_us: float | None,
                   warn: Warn | None) -> None:
        self.tick_hz = 1_000_000_000
        if self.gige:
            self.tick_hz = int(_get(self.cam, ("GevTimestampTickFrequency",)) or self.tick_hz)
        if exposure_us is not None:
            _set(self.cam, ("ExposureAuto",), "Off")
            if not _set(self.cam, ("ExposureTime", "ExposureTimeAbs"), float(exposure_us)):
                raise UserError(f"Basler camera {self.serial}: the exposure time could not "
                                f"be set to {exposure_us:g} us")
        if fps is not None:
            _set(self.cam, ("AcquisitionFrameRateEnable",), True)
            if not _set(self.cam, ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"),
                        float(fps)):
                raise UserError(f"Basler camera {self.serial}: the frame rate could not be "
                                f"set to {fps:g} fps")
        got = _get(self.cam, ("ResultingFrameRate", "ResultingFrameRateAbs"))
        self.fps = float(got) if got else None
        if fps is not None and warn is not None and got is not None and rate_differs(fps, got):
            warn(f"Basler camera {self.serial}: asked for {fps:g} fps, it runs at "
                 f"{float(got):g} fps (exposure or bandwidth limit it)")

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        block_ids = BlockIds(self.gige)
        while self.cam.IsGrabbing():
            res = self.cam.RetrieveResult(2000, self.pylon.TimeoutHandling_ThrowException)
            try:
                if res.GrabSucceeded():
                    arrival = time.monotonic_ns()
                    device_ns, frame_id = stamps(res, self.tick_hz, block_ids)
                    yield Frame(self.camera, i, arrival, res.Array.copy(), device_ns,
                                frame_id)
                    i += 1
            finally:
                res.Release()

    def close(self) -> None:
        try:
            self.cam.StopGrabbing()
        finally:
            self.cam.Close()
