"""The daemon's control socket: one JSON request per connection, one JSON answer.

A Unix socket (mode 0600) under the runtime directory, answering status, stop, reload,
record, record_stop and markers (daemon.service.Daemon.handle); `request` is the client
side that `mocapd status`, `rigid-body add` and the live view use.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.config import default_runtime_dir

log = logging.getLogger("mocapd")
SOCKET_NAME = "mocapd.sock"


def _read_message(sock: socket.socket) -> bytes:
    """One control-socket message: bytes up to a newline, or to the peer's close."""
    data = b""
    while not data.endswith(b"\n"):
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
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
        self.thread: threading.Thread | None = None

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
        self.thread = threading.Thread(target=self._serve, name="control", daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while self.sock is not None:
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            with conn:
                try:
                    conn.settimeout(2.0)
                    data = _read_message(conn)
                    try:
                        answer = self.handler(json.loads(data or b"{}"))
                    except UserError as exc:
                        answer = {"ok": False, "error": str(exc)}
                    except Exception as exc:  # noqa: BLE001 - never kill the server
                        log.exception("control request failed")
                        answer = {"ok": False, "error": f"internal error: {exc}"}
                    conn.sendall(json.dumps(answer, default=_plain).encode() + b"\n")
                except OSError:
                    pass

    def close(self) -> None:
        sock, self.sock = self.sock, None
        if sock is not None:
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
