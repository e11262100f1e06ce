"""Serial output: the pose packet with CRC-16, COBS-framed (Arduino PacketSerial reads it)."""

from __future__ import annotations

from daemon.publish.base import Publisher
from daemon.publish.packet import serial_frame
from daemon.publish.udp import result_packet


def open_port(device: str, baud: int, write_timeout_s: float = 0.2):
    """A pyserial port; a write that cannot finish in write_timeout_s raises, so a
    consumer that stopped reading is noticed, not waited for."""
    # deferred on purpose: loads pyserial only where used
    import serial

    return serial.serial_for_url(device, baudrate=baud, timeout=0,
                                 write_timeout=write_timeout_s)


class SerialPublisher(Publisher):
    def __init__(self, device: str, baud: int = 115200, rate_hz: float = 100.0,
                 bodies: list[int] | None = None, name: str | None = None) -> None:
        super().__init__(rate_hz=rate_hz)
        self.device, self.baud, self.bodies = device, baud, bodies
        self.name = name or f"serial:{device}"
        self.port = None

    def open(self) -> None:
        self.port = open_port(self.device, self.baud)

    def send(self, result) -> None:
        self.port.write(serial_frame(result_packet(result, self.bodies)))

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
            self.port = None
