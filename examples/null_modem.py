"""Two pseudo-terminals joined like a null-modem cable: what mocapd writes to one, a robot
program reads from the other (the simulator's stand-in for a UART or a radio link).

    python examples/null_modem.py          # prints the two device paths, runs until Ctrl-C

Give mocapd the first (`[[serial]] device = ...` or `--serial PATH`) and the robot program
the second. `socat -d -d pty,raw,echo=0 pty,raw,echo=0` does the same where socat is
installed. `tap` (a file) records what goes from the first to the second, as a logic
analyser on the wire would.
"""

from __future__ import annotations

import argparse
import os
import select
import sys
import threading
import tty


class NullModem:
    """Two ptys whose masters are bridged by a thread; `a` and `b` are the device paths."""

    def __init__(self, tap: str | None = None) -> None:
        self.ends = [os.openpty(), os.openpty()]
        for master, slave in self.ends:
            tty.setraw(slave)  # no echo, no line editing: a byte stream, as a UART
            os.set_blocking(master, False)  # nobody reading an end: its bytes are lost
        self.a, self.b = (os.ttyname(s) for _, s in self.ends)
        self.tap = open(tap, "wb") if tap else None
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, name="null-modem", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        (ma, _), (mb, _) = self.ends
        other = {ma: mb, mb: ma}
        while not self.stop_event.is_set():
            ready, _, _ = select.select([ma, mb], [], [], 0.1)
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    continue
                if self.tap is not None and fd == ma:
                    self.tap.write(data)
                try:
                    os.write(other[fd], data)
                except OSError:
                    pass  # the far end's buffer is full: lost, as on a wire

    def close(self) -> None:
        self.stop_event.set()
        self.thread.join(1.0)
        if self.tap is not None:
            self.tap.close()
        for pair in self.ends:
            for fd in pair:
                os.close(fd)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tap", help="record what goes from the first end to the second here")
    args = ap.parse_args()
    modem = NullModem(args.tap)
    print(f"mocapd end: {modem.a}\nrobot end:  {modem.b}", flush=True)
    try:
        modem.stop_event.wait()
    except KeyboardInterrupt:
        pass
    modem.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
