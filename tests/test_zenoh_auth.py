"""Who may join the daemon's Zenoh session (daemon/publish/zenoh_session.py): the users file and the
credentials are checked at start in one line each; on loopback, a peer without a listed
user's password delivers nothing (the namespace test in test_nodes_link.py runs the nodes)."""

from __future__ import annotations

import logging
import time

import pytest
from test_nodes import free_port

from calibkit.core.errors import UserError
from daemon.config.mocapd import load_config
from daemon.nodes.settings import load_node_config
from daemon.publish.zenoh_session import ZenohSettings


def test_the_keys_are_checked_at_start(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("node-a:pw one\n\nnode-b:pw2\n")
    good = tmp_path / "mocapd.toml"
    good.write_text('[zenoh]\nusers_file = "users.txt"\n')
    assert load_config(good).zenoh.session.users_file == str(users)
    for text, words in ((f"# nodes\n{users.read_text()}", "line 1: expected user:password"),
                        ("node-a pw\n", "line 1"), (" node-a:pw\n", "no spaces"), ("", "no user")):
        users.write_text(text)
        with pytest.raises(UserError, match="zenoh.users_file") as err:
            load_config(good)
        assert words in str(err.value) and "\n" not in str(err.value)
    missing = tmp_path / "m.toml"
    missing.write_text('[zenoh]\nusers_file = "nobody.txt"\n')
    with pytest.raises(UserError, match="cannot read"):
        load_config(missing)
    node = tmp_path / "node.toml"
    node.write_text('[zenoh]\nuser = "node-a"\n')
    with pytest.raises(UserError, match="zenoh.password"):
        load_node_config(node)


def test_only_listed_users_deliver_on_loopback(tmp_path, caplog):
    users = tmp_path / "users.txt"
    users.write_text("node-a:correct horse\n")
    port = free_port()
    daemon_side = ZenohSettings("t", listen=(f"tcp/127.0.0.1:{port}",), users_file=str(users))
    assert daemon_side.exposed() == []
    open_side = ZenohSettings("t", listen=("tcp/0.0.0.0:1",))
    assert open_side.exposed() == ["tcp/0.0.0.0:1"]
    got: list[bytes] = []
    server = daemon_side.open()
    sub = server.declare_subscriber("mocap/t/**", lambda s: got.append(bytes(s.payload)))
    try:
        results = {}
        for name, user, password in (("listed", "node-a", "correct horse"),
                                     ("wrong", "node-a", "guess"), ("none", "", "")):
            got.clear()
            peer = ZenohSettings("t", connect=(f"tcp/127.0.0.1:{port}",), user=user,
                                 password=password).open()
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline and not got:
                peer.put("mocap/t/cam0/blobs", name.encode())
                time.sleep(0.05)
            results[name] = len(got)
            peer.close()
    finally:
        sub.undeclare()
        server.close()
    assert results["listed"] > 0 and results["wrong"] == 0 and results["none"] == 0
    with caplog.at_level(logging.WARNING, "mocapd"):
        s = ZenohSettings("t", listen=(f"tcp/0.0.0.0:{free_port()}",)).open()
        s.close()
    assert "no access control" in caplog.text
