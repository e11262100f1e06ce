"""The control socket (daemon/service/control.py): idle or hostile clients hold up nobody, malformed
requests get an error answer and one log line a minute, never a traceback."""

from __future__ import annotations

import json
import logging
import socket

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibkit.core.errors import UserError
from daemon.service.control import ControlServer, request


def _handler(req: dict) -> dict:
    if req.get("cmd") == "status":
        return {"ok": True, "frames": 7}
    if req.get("cmd") == "record":
        return {"ok": True, "path": str(req["path"])}  # KeyError without a path
    raise UserError(f"unknown request {req.get('cmd')!r}")


def _raw(path, data: bytes) -> bytes:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(path))
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out


def test_idle_clients_never_block_a_status(tmp_path):
    server = ControlServer(tmp_path, _handler)
    server.open()
    idle = []
    try:
        for _ in range(5):  # connect and say nothing, as a stuck script might
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(server.path))
            idle.append(s)
        assert request(tmp_path, {"cmd": "status"}, timeout_s=1.5)["frames"] == 7
    finally:
        for s in idle:
            s.close()
        server.close()


def test_malformed_requests_are_answered_and_logged_once(tmp_path, caplog):
    server = ControlServer(tmp_path, _handler)
    server.open()
    try:
        with caplog.at_level(logging.INFO, "mocapd"):
            answers = [json.loads(_raw(server.path, junk)) for junk in (
                b"not json\n", b"[1, 2]\n", b'{"cmd": 5}\n', b"\xff\xfe\n",
                b'{"cmd": "record"}\n', b'"status"\n')]

            @settings(max_examples=200, deadline=None,
                      suppress_health_check=[HealthCheck.function_scoped_fixture])
            @given(st.binary(max_size=200))
            def fuzz(data):
                answer = json.loads(_raw(server.path, data + b"\n"))
                assert "ok" in answer

            fuzz()
        assert all(a["ok"] is False and a["error"] for a in answers)
        assert request(tmp_path, {"cmd": "status"})["frames"] == 7  # still serving
    finally:
        server.close()
    assert not [r for r in caplog.records if r.exc_info]  # no traceback
    kinds = [r.getMessage().split("(")[0] for r in caplog.records]
    assert len(kinds) == len(set(kinds)) <= 2  # one line per kind of bad request
