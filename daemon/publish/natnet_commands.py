"""Motive's command strings (NAT_REQUEST) as mocapd answers them, and what they set per client.

Why answer them and not refuse: NatNet clients send Motive's commands as a matter of
course (the SDK's sample asks the bitstream and sends TimelinePlay after a version change,
ROS drivers ask FrameRate, recording tools send StartRecording), and a client told
"unrecognised" often gives up. Each command gets the answer Motive gives where mocapd can
honour it, and a failure (-1) where it cannot; none is acknowledged and then ignored.

Answers: an int32 result (0 success, -1 failure), a float32 for FrameRate and
UnitsToMillimeters, or text without a terminating NUL ("Bitstream,4.1": the SDK's
PacketClient reads the text to the end of the datagram).
"""

from __future__ import annotations

import ipaddress
import logging
import re
import struct
import time
from dataclasses import replace
from pathlib import Path

from calibkit.core.errors import UserError
from daemon.publish.bad_input import BadInput
from daemon.publish.natnet_wire import (
    DEFAULT_VERSION,
    EVERYTHING,
    NAT_RESPONSE,
    View,
    message,
    parse_version,
    same_frames,
    served,
)

log = logging.getLogger("mocapd.publish")

OK, FAILED = 0, -1
# a live system has no timeline: these change nothing, as in Motive's live mode
LIVE_NOOPS = ("timelineplay", "timelinestop", "setplaybackcurrentframe",
              "setplaybackstartframe", "setplaybackstopframe", "setplaybacklooping",
              "livemode")
DATA_TYPES = ("rigidbody", "skeleton", "forceplate", "device", "labeledmarkers",
              "markersetmarkers", "legacyunlabeledmarkers", "alltypes")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 _.-]{0,63}$")
# what only an allowed address may send: they write to the disk
RECORDING = ("setrecordtakename", "setcurrentsession", "startrecording", "stoprecording")
BUDGET_CHECK_S = 0.5  # how often a NatNet-started recording's duration and size are looked at


def networks(addresses) -> tuple:
    """The allowed senders of recording commands: addresses or networks ("10.0.0.0/24");
    raises ValueError naming the first that is neither."""
    return tuple(ipaddress.ip_network(a, strict=False) for a in addresses)


def code(value: int) -> bytes:
    return message(NAT_RESPONSE, struct.pack("<i", value))


def real(value: float) -> bytes:
    return message(NAT_RESPONSE, struct.pack("<f", value))


def text(value: str) -> bytes:
    return message(NAT_RESPONSE, value.encode("utf-8"))


class Commands:
    """The answers, and the state commands set: each client's bitstream version and data
    subscription (by its address), the take name and session for recordings.

    `bodies` (BodyDef) resolve subscriptions by name; `control` is the daemon's control
    request handler (daemon.service.daemon.Daemon.handle), through which StartRecording and
    StopRecording record as `mocapd record` does, into `record_dir`.

    Recording writes to the disk, so its commands are taken only from `record_from`
    (addresses or networks; loopback by default) and a take it starts stops by itself after
    `record_max_s` seconds or `record_max_mb` megabytes (0: no limit), whichever comes
    first: a client that starts a take and goes away does not fill the disk."""

    def __init__(self, fps: float, bodies=(), record_dir: Path | None = None,
                 control=None, record_from=("127.0.0.1",), record_max_s: float = 3600.0,
                 record_max_mb: float = 2000.0) -> None:
        self.fps = float(fps)
        self.body_ids = {b.name: int(b.id) for b in bodies}
        self.record_dir = None if record_dir is None else Path(record_dir)
        self.control = control
        self.versions: dict[tuple, tuple[int, int]] = {}
        self.views: dict[tuple, View] = {}
        self.take: str | None = None
        self.session: str | None = None
        self.recording: str | None = None  # the path being recorded
        self.record_from = networks(record_from)
        self.record_max_s, self.record_max_mb = float(record_max_s), float(record_max_mb)
        self.bad = BadInput(log, "NatNet")
        self._started = 0.0  # monotonic time the recording started
        self._next_check = 0.0
        self.budget_stops = 0

    def version(self, addr) -> tuple[int, int]:
        return self.versions.get(addr, DEFAULT_VERSION)

    def view(self, addr) -> View:
        return self.views.get(addr, EVERYTHING)

    def forget(self, addr) -> None:
        self.versions.pop(addr, None)
        self.views.pop(addr, None)

    def answer(self, request: str, addr, unicast: bool) -> bytes | None:
        """The NAT_RESPONSE to one command; None when the command is not Motive's."""
        word, _, arg = request.partition(",")
        word = word.strip().lower()
        args = [a.strip() for a in arg.split(",")] if arg.strip() else []
        if word in RECORDING and not self.may_record(addr):
            self.bad("recording command from an address not in record_from",
                     f"{word} from {addr[0]}")
            return code(FAILED)
        if word == "bitstream":
            return self._bitstream(args, addr, unicast)
        if word == "framerate":
            return real(self.fps)
        if word == "unitstomillimeters":
            return real(1000.0)  # positions are in metres
        if word == "currentmode":
            return code(0)  # live
        if word == "analogsamplespermocapframe":
            return code(0)  # no analog devices
        if word in LIVE_NOOPS:
            return code(OK)
        if word in ("editmode", "setplaybacktakename"):
            return code(FAILED)  # no takes to play back: live only
        if word in ("subscribetodata", "subscribebyid", "subscribeddataonly"):
            return code(self._subscribe(word, args, addr, unicast))
        if word == "setrecordtakename":
            return code(self._set_name("take", args))
        if word == "setcurrentsession":
            return code(self._set_name("session", args))
        if word == "startrecording":
            return code(self._start_recording())
        if word == "stoprecording":
            return code(self._stop_recording())
        self.bad("unrecognised command", word[:40])
        return None

    def may_record(self, addr) -> bool:
        try:
            ip = ipaddress.ip_address(addr[0])
        except (ValueError, TypeError, IndexError):
            return False
        return any(ip in net for net in self.record_from)

    # ---- bitstream -------------------------------------------------------------------------

    def _bitstream(self, args, addr, unicast: bool) -> bytes:
        if not args:  # a query: the version this client is served
            major, minor = self.version(addr)
            return text(f"Bitstream,{major}.{minor}")
        wanted = parse_version(args[0])
        if wanted is None or not served(wanted):
            return code(FAILED)
        if not unicast and not same_frames(wanted, DEFAULT_VERSION):
            return code(FAILED)  # its frames come by multicast, in the default version
        self.versions[addr] = wanted
        return code(OK)

    # ---- subscriptions (unicast) ------------------------------------------------------------

    def _subscribe(self, word: str, args, addr, unicast: bool) -> int:
        if not unicast:
            return FAILED  # Motive subscribes unicast clients only
        view = self.views.get(addr)
        if word == "subscribeddataonly":
            self.views[addr] = View(frozenset(), False, frozenset(), False) \
                if view is None else view
            return OK
        kind = args[0].lower() if args else ""
        name = args[1] if len(args) > 1 else ""
        if kind not in DATA_TYPES or (word == "subscribebyid" and kind != "rigidbody"):
            return FAILED
        if view is None:  # the first subscription: from now on only what is subscribed
            view = View(frozenset(), False, frozenset(), False)
        everything = name.lower() in ("", "all")
        nothing = name.lower() == "none"
        if kind in ("rigidbody", "alltypes"):
            if word == "subscribebyid":
                if not name.lstrip("-").isdigit():
                    return FAILED
                ids = {int(name)}
            elif everything or nothing:
                ids = None
            elif name in self.body_ids:
                ids = {self.body_ids[name]}
            else:
                return FAILED
            if nothing:
                view = replace(view, bodies=frozenset())
            elif ids is None:
                view = replace(view, bodies=None)
            elif view.bodies is not None:
                view = replace(view, bodies=view.bodies | ids)
        if kind in ("labeledmarkers", "alltypes"):
            view = replace(view, labeled=not nothing)
        if kind in ("legacyunlabeledmarkers", "alltypes"):
            view = replace(view, legacy=not nothing)
        if kind in ("markersetmarkers", "alltypes"):
            if nothing:
                view = replace(view, marker_sets=frozenset())
            elif everything or kind == "alltypes":
                view = replace(view, marker_sets=None)
            elif view.marker_sets is not None:
                view = replace(view, marker_sets=view.marker_sets | {name})
        self.views[addr] = view  # skeletons, force plates, devices: there are none to send
        return OK

    # ---- recording --------------------------------------------------------------------------

    def _set_name(self, what: str, args) -> int:
        name = args[0] if args else ""
        if not _NAME.match(name):
            self.bad(f"{what} name that is not letters, digits, space, _ . -", repr(name))
            return FAILED
        setattr(self, what, name)
        return OK

    def _start_recording(self) -> int:
        if self.control is None or self.record_dir is None:
            self.bad("StartRecording without record_dir in [natnet] (set it to record takes)")
            return FAILED
        folder = self.record_dir / self.session if self.session else self.record_dir
        take = self.take or time.strftime("take_%Y-%m-%d_%H-%M-%S")
        path = folder / f"{take}.mcrec"
        n = 1
        while path.exists():  # never over an earlier take
            path = folder / f"{take}_{n:03d}.mcrec"
            n += 1
        try:
            folder.mkdir(parents=True, exist_ok=True)
            self.control({"cmd": "record", "path": str(path)})
        except (UserError, OSError) as exc:
            log.warning("NatNet: StartRecording failed: %s", exc)
            return FAILED
        self.recording = str(path)
        self._started = time.monotonic()
        log.info("NatNet: recording to %s", path)
        return OK

    def check_budget(self) -> None:
        """Stop a recording StartRecording began once it is older than record_max_s or
        larger than record_max_mb (looked at every BUDGET_CHECK_S)."""
        now = time.monotonic()
        path = self.recording
        if path is None or now < self._next_check:
            return
        self._next_check = now + BUDGET_CHECK_S
        over = None
        if self.record_max_s > 0 and now - self._started >= self.record_max_s:
            over = f"{self.record_max_s:g} s (record_max_s)"
        elif self.record_max_mb > 0:
            try:
                size_mb = Path(path).stat().st_size / 1e6
            except OSError:
                size_mb = 0.0  # not written yet
            if size_mb >= self.record_max_mb:
                over = f"{self.record_max_mb:g} MB (record_max_mb)"
        if over is not None:
            log.warning("NatNet: the take %s reached %s: stopping it", path, over)
            self.budget_stops += 1
            self._stop_recording()

    def _stop_recording(self) -> int:
        if self.control is None:
            return FAILED
        try:
            answer = self.control({"cmd": "record_stop"})
        except UserError:
            self.recording = None
            return FAILED  # nothing was recording
        log.info("NatNet: recorded %d frames to %s", answer.get("frames", 0),
                 answer.get("path"))
        self.recording = None
        return OK
