"""Serial line budgets: what an output puts on a UART each second, and the rate that fits.

Why check before sending: a UART carries baud / 10 bytes a second (8N1: a start bit, eight
data bits, a stop bit) and not one more. A configuration that asks for more does not fail
anywhere visible: the kernel's buffer fills, writes time out now and then, and the
microcontroller or autopilot at the other end gets late, partial frames. So the daemon
refuses a rate that cannot fit, saying what would, and picks the highest rate that fits
when the rate is left to it (`rate_hz = "auto"`, the default).
"""

from __future__ import annotations

import math
from dataclasses import replace

from daemon.publish.packet import BODY_SIZE, HEADER_SIZE

BITS_PER_BYTE = 10  # 8N1
AUTO_SHARE = 0.9  # an automatic rate leaves a tenth of the line free (clock drift, jitter)
MAVLINK_FRAMING = 12  # MAVLink 2: 10 header bytes and a 2-byte CRC around the payload
# what a MAVLink link sends besides the poses: HEARTBEAT at 1 Hz (9-byte payload) and up to
# 10 TIMESYNC messages a second (16 bytes: our own requests and answers to the autopilot's)
MAVLINK_OVERHEAD_BYTES_PER_S = (9 + MAVLINK_FRAMING) + 10 * (16 + MAVLINK_FRAMING)
NETWORK_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:")


def line_bytes_per_s(baud: int) -> float:
    return baud / BITS_PER_BYTE


def serial_frame_bytes(n_bodies: int) -> int:
    """A COBS-framed pose packet on the wire, at most: packet, CRC-16, COBS's code bytes
    (one per 254 bytes and one more), the zero delimiter."""
    raw = HEADER_SIZE + BODY_SIZE * n_bodies + 2
    return raw + raw // 254 + 1 + 1


def mavlink_frame_bytes(message: str) -> int:
    """The longest MAVLink 2 frame of a message (no zero trimming, unsigned)."""
    # deferred on purpose: loads pymavlink only where used
    from pymavlink.dialects.v20 import common

    return getattr(common, f"MAVLink_{message}_message").unpacker.size + MAVLINK_FRAMING


def fitting_rate_hz(frame_bytes: int, baud: int, overhead_bytes_per_s: float = 0.0,
                    share: float = 1.0) -> float:
    """The highest whole rate whose frames (and the overhead) fill at most `share` of the
    line; 0 when not even the overhead fits."""
    room = line_bytes_per_s(baud) * share - overhead_bytes_per_s
    return max(0.0, float(math.floor(room / frame_bytes)))


def smallest_baud(bytes_per_s: float) -> int:
    """The smallest common baud rate that carries `bytes_per_s`."""
    for baud in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600,
                 1000000, 1500000, 2000000, 3000000, 4000000):
        if line_bytes_per_s(baud) >= bytes_per_s:
            return baud
    return 0


def is_serial_device(device: str) -> bool:
    """A device path (a UART), not a network address in mavutil's notation."""
    return not device.startswith(NETWORK_PREFIXES)


def _refusal(what: str, need_bytes_per_s: float, baud: int, fits_hz: float,
             fewer: str) -> str:
    faster = smallest_baud(need_bytes_per_s)
    return (f"{what} needs {need_bytes_per_s / 1000:.1f} kB/s but {baud} baud carries "
            f"{line_bytes_per_s(baud) / 1000:.1f} kB/s; set rate_hz to at most "
            f"{fits_hz:g}{fewer}, raise baud" + (f" ({faster} fits)" if faster else "")
            + ', or set rate_hz = "auto"')


def fit_serial(out, n_bodies: int, fps: float, default_hz: float = 100.0):
    """A [[serial]] output (daemon.config.outputs.SerialOut) with its rate checked against its
    line: "auto" (None) becomes the highest rate up to `default_hz` (and the cameras'
    `fps`) that fills at most AUTO_SHARE of it; 0 (every frame) is `fps`. Returns (output,
    note for the log or None); ValueError when a rate given does not fit."""
    frame = serial_frame_bytes(n_bodies)
    default_hz = min(default_hz, fps)
    what = f"{n_bodies} {'body' if n_bodies == 1 else 'bodies'} ({frame}-byte frames)"
    if out.rate_hz is None:
        hz = min(default_hz, fitting_rate_hz(frame, out.baud, share=AUTO_SHARE))
        if hz < 1:
            raise ValueError(_refusal(f"{what} at 1 Hz", frame, out.baud, 0, "") )
        return replace(out, rate_hz=hz), f"{what} at {hz:g} Hz fit {out.baud} baud (auto)"
    rate = out.rate_hz or fps
    need = frame * rate
    if need > line_bytes_per_s(out.baud):
        shown = f"{rate:g} Hz" + (" (every frame)" if not out.rate_hz else "")
        raise ValueError(_refusal(f"{what} at {shown}", need, out.baud,
                                  fitting_rate_hz(frame, out.baud),
                                  ", send fewer bodies (bodies = [ids])"))
    return out, None


def fit_mavlink(out, fps: float, default_hz: float = 50.0):
    """A [[mavlink]] output (daemon.config.outputs.MavlinkOut) checked as fit_serial checks a
    serial one, counting HEARTBEAT and TIMESYNC too; outputs over UDP or TCP pass as
    they are ("auto": `default_hz`)."""
    default_hz = min(default_hz, fps)
    if not is_serial_device(out.device):
        return (replace(out, rate_hz=default_hz), None) if out.rate_hz is None else (out, None)
    frame = mavlink_frame_bytes(out.message)
    what = f"{out.message.upper()} ({frame}-byte frames)"
    over = MAVLINK_OVERHEAD_BYTES_PER_S
    if out.rate_hz is None:
        hz = min(default_hz, fitting_rate_hz(frame, out.baud, over, AUTO_SHARE))
        if hz < 1:
            raise ValueError(_refusal(f"{what} at 1 Hz", frame + over, out.baud, 0, ""))
        return replace(out, rate_hz=hz), f"{what} at {hz:g} Hz fit {out.baud} baud (auto)"
    rate = out.rate_hz or fps
    need = frame * rate + over
    if need > line_bytes_per_s(out.baud):
        raise ValueError(_refusal(f"{what} at {rate:g} Hz with HEARTBEAT and "
                                  "TIMESYNC", need, out.baud,
                                  fitting_rate_hz(frame, out.baud, over), ""))
    return out, None
