"""`mocapd install-unit`: ExecStart quoted as systemd reads it, the right follow-up command."""

from __future__ import annotations

import shlex
import shutil
import subprocess

import pytest

from calibkit.core.errors import UserError
from daemon.commands.unit_cmd import exec_line, systemd_quote


def systemd_words(line: str) -> list[str]:
    """ExecStart= words as systemd reads them: quotes and backslashes as a POSIX shell's
    double quotes, then `%%` and `$$` back to one character."""
    return [w.replace("%%", "%").replace("$$", "$") for w in shlex.split(line)]


def test_words_with_spaces_quotes_and_specifiers_come_back_whole():
    words = ["/opt/my tools/mocapd", "start", "--config", '/srv/lab "A"/50%/$HOME\\x.toml']
    line = exec_line(words)
    assert systemd_words(line) == words
    assert "%%" in line and "$$HOME" in line  # no specifier, no variable left for systemd
    assert systemd_quote("/etc/mocapd/mocapd.toml") == "/etc/mocapd/mocapd.toml"
    with pytest.raises(UserError, match="control character"):
        systemd_quote("a\nb")


def _unit(tmp_path, mocapd_cli, out):
    cfg_dir = tmp_path / "mocap lab" / "100%"
    cfg_dir.mkdir(parents=True)
    config = cfg_dir / "my $cfg.toml"
    config.write_text("[sim]\ncameras = 3\n")
    # the kernels' build is tests/test_daemon_e2e.py's (test_install_unit)
    r = mocapd_cli("install-unit", "--config", config, "--out", out, "--no-build-kernels")
    assert r.code == 0, r.err
    return config, r.out


def test_system_unit_quotes_its_paths_and_says_the_system_commands(tmp_path, mocapd_cli):
    out = tmp_path / "units dir" / "mocap-a.service"
    config, printed = _unit(tmp_path, mocapd_cli, out)
    line = next(t for t in out.read_text().splitlines() if t.startswith("ExecStart="))
    words = systemd_words(line.removeprefix("ExecStart="))
    # the installed daemon is the one that runs real-time (a terminal's or --sim's is not)
    assert words[-4:] == ["start", "--config", str(config.resolve()), "--realtime"]
    assert "--user" not in printed and "WantedBy=multi-user.target" in out.read_text()
    follow = printed.splitlines()[-1]
    assert follow.startswith("then: systemctl link ") and follow.endswith(
        "systemctl daemon-reload && systemctl enable --now mocap-a.service")
    assert systemd_words(follow.removeprefix("then: systemctl link ").split(" && ")[0]) == [
        str(out.resolve())]
    if shutil.which("systemd-analyze"):  # systemd's own parser agrees (it rejects %x)
        r = subprocess.run(["systemd-analyze", "verify", str(out)], capture_output=True,
                           text=True)
        assert r.returncode == 0, r.stderr


def test_user_unit_says_the_user_commands(tmp_path, mocapd_cli):
    out = tmp_path / ".config/systemd/user/mocapd.service"
    _, printed = _unit(tmp_path, mocapd_cli, out)
    assert printed.splitlines()[-1] == ("then: systemctl --user daemon-reload && "
                                        "systemctl --user enable --now mocapd.service")
    assert "WantedBy=default.target" in out.read_text()
