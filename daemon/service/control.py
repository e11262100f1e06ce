"""The daemon's control socket: one JSON request per connection, one JSON answer.

A Unix socket (mode 0600) under the runtime directory, answering status, stop, reload,
record, record_stop and markers (daemon.service.daemon.Daemon.handle); `request` is the client
side that `mocapd status`, `rigid-body add` and the live view use.

Each connection is served on a thread of its own, so a client that connects and says
nothing holds up nobody (it was served one at a time: an idle client blocked `mocapd
status`); requests are bounded in size and in how many are served at once, and a malformed
one is answered with an error and logged once a minute, without a traceback.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.config.mocapd import default_runtime_dir
from daemon.process.supervise import Supervised

log = logging.getLogger("mocapd")
SOCKET_NAME = "mocapd.sock"


MAX_MESSAGE = 1 << 20  # a request is a line of JSON; an answer (status) is a few kB
MAX_CLIENTS = 16  # served at once; more are closed at once


def _read_message(sock: socket.socket, limit: int = 64 * MAX_MESSAGE) -> bytes:
    """One control-socket message: bytes up to a newline, or to the peer's close."""
    data = b""
    while not data.endswith(b"\n"):
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
        if len(data) > limit:
            raise ValueError(f"a message over {limit} bytes")
    return data


def request(runtime_dir: Path | None, message: dict, timeout_s: float = 5.0) -> dict:
    """Send one request to a running daemon's control socket; its JSON answer."""
    path = Path(runtime_dir or default_runtime_dir()) / SOCKET_NAME
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(timeout_s)
            s.connect(str(path))
            s.sendall(json.dumps(message).encode() + b"\n")
            data = _read_message(s)
    except (FileNotFoundError, ConnectionRefusedError):
        raise UserError(f"no mocapd running (no control socket at {path}); start one with "
                        "`mocapd start`, or pass --runtime-dir") from None
    except OSError as exc:
        raise UserError(f"cannot talk to mocapd at {path}: {exc}") from None
    try:
        answer = json.loads(data)
    except json.JSONDecodeError:
        raise UserError(f"mocapd at {path} sent a malformed answer") from None
    if not answer.get("ok", False):
        raise UserError(f"mocapd: {answer.get('error', 'request failed')}")
    return answer


class ControlServer:
    """Accepts one JSON request per connection and answers with handler(request)."""

    def __init__(self, runtime_dir: Path, handler) -> None:
        self.dir = Path(runtime_dir)
        self.path = self.dir / SOCKET_NAME
        self.handler = handler
        self.sock: socket.socket | None = None
        self.thread: Supervised | None = None
        self.supervised: list = []
        self._slots = threading.BoundedSemaphore(MAX_CLIENTS)
        self._handling = threading.Lock()
        self._logged: dict[str, float] = {}  # kind of bad request -> when last logged

    def open(self) -> None:
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        if self.path.exists():
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.connect(str(self.path))
                raise UserError(f"another mocapd is running (control socket {self.path}); "
                                "stop it with `mocapd stop` or use another --runtime-dir")
            except (ConnectionRefusedError, FileNotFoundError):
                self.path.unlink(missing_ok=True)  # left over from a killed daemon
            finally:
                probe.close()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)
        try:
            sock.bind(str(self.path))
        except OSError as exc:
            sock.close()
            raise UserError(f"cannot create the control socket {self.path}: {exc}") from None
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        sock.listen(8)
        sock.settimeout(0.2)
        self.sock = sock
        self.thread = Supervised("control", self._serve,
                                 stopping=lambda: self.sock is None).start()
        self.supervised = [self.thread]

    def _serve(self) -> None:
        while self.sock is not None:
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            if not self._slots.acquire(blocking=False):
                self._once("busy", "control socket: %d clients at once; closing another",
                           MAX_CLIENTS)
                conn.close()
                continue
            try:
                threading.Thread(target=self._serve_one, args=(conn,), name="control-client",
                                 daemon=True).start()
            except BaseException:  # no thread to be had: the slot back, the server restarted
                self._slots.release()
                conn.close()
                raise

    def _serve_one(self, conn: socket.socket) -> None:
        try:
            with conn:
                conn.settimeout(2.0)
                try:
                    data = _read_message(conn, MAX_MESSAGE)
                    req = json.loads(data or b"{}")
                    if not isinstance(req, dict) or not isinstance(req.get("cmd", ""), str):
                        raise ValueError("not a JSON object with a string 'cmd'")
                except (ValueError, UnicodeDecodeError) as exc:
                    self._once("malformed", "control socket: a malformed request (%s)", exc)
                    answer = {"ok": False, "error": f"malformed request: {exc}"}
                else:
                    answer = self._answer(req)
                conn.sendall(json.dumps(answer, default=_plain).encode() + b"\n")
        except OSError:
            pass  # the client went away (or never spoke within the timeout)
        finally:
            self._slots.release()

    def _answer(self, req: dict) -> dict:
        try:
            with self._handling:  # one request at a time reaches the daemon, as before
                return self.handler(req)
        except UserError as exc:
            return {"ok": False, "error": str(exc)}
        except (KeyError, TypeError, ValueError) as exc:  # a request with wrong values
            self._once("bad values", "control socket: a request with bad values (%s)", exc)
            return {"ok": False, "error": f"bad request: {exc}"}
        except Exception as exc:  # noqa: BLE001 - never kill the server
            if self._due("internal"):
                log.exception("control request failed")
            return {"ok": False, "error": f"internal error: {exc}"}

    def _due(self, kind: str) -> bool:
        now = time.monotonic()
        if now - self._logged.get(kind, -1e9) < 60.0:
            return False
        self._logged[kind] = now
        return True

    def _once(self, kind: str, message: str, *args) -> None:
        """Log a kind of bad input at most once a minute: junk must not flood the log."""
        if self._due(kind):
            log.warning(message, *args)

    def close(self) -> None:
        sock, self.sock = self.sock, None
        if sock is not None:
            try:  # wakes the accept waiting on it now, not at its next 0.2 s timeout
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        if self.thread is not None:
            self.thread.join(1.0)
        self.path.unlink(missing_ok=True)


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
