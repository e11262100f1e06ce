"""Log lines for the journal (syslog priority prefixes) and rich tables and progress."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

from daemon.process.logs import setup_logging, writes_to_journal
from daemon.service.console import Progress, print_table

ROOT = Path(__file__).resolve().parents[1]


def _journal_env(path: Path) -> str:
    st = os.stat(path)
    return f"{st.st_dev}:{st.st_ino}"


def test_priority_prefix_only_on_the_journal_stream(tmp_path, monkeypatch):
    path = tmp_path / "stderr"
    log = logging.getLogger("mocapd.test")
    with open(path, "w") as stream:
        monkeypatch.setenv("JOURNAL_STREAM", _journal_env(path))
        assert writes_to_journal(stream)
        setup_logging(verbose=True, stream=stream)
        log.debug("looking")
        log.info("tracking")
        log.warning("serial: cannot open\nsecond line")
        log.error("reload failed")
        stream.flush()
    assert path.read_text().splitlines() == ["<7>looking", "<6>tracking",
                                             "<4>serial: cannot open", "<4>second line",
                                             "<3>reload failed"]
    other = tmp_path / "other"
    with open(other, "w") as stream:  # the variable names another stream: plain lines
        assert not writes_to_journal(stream)
        setup_logging(stream=stream)
        log.warning("serial: cannot open")
        stream.flush()
    assert other.read_text() == "mocapd: serial: cannot open\n"
    monkeypatch.setenv("JOURNAL_STREAM", "garbage")
    assert not writes_to_journal(open(path))
    setup_logging(stream=sys.stderr)


def test_mocapd_start_under_the_journal(tmp_path):
    """A real run with stderr on the 'journal' stream: every line carries its priority;
    the warning about a serial device that is not there is priority 4."""
    err = tmp_path / "journal"
    err.touch()
    env = dict(os.environ, JOURNAL_STREAM=_journal_env(err), PYTHONPATH=str(ROOT))
    with open(err, "w") as stream:
        r = subprocess.run([sys.executable, "-m", "daemon.cli", "start", "--sim", "--fast",
                            "--frames", "60", "--sim-cameras", "3", "--sim-bodies", "1",
                            "--serial", str(tmp_path / "no-such-tty"), "--runtime-dir",
                            tmp_path / "rt"], stdout=subprocess.PIPE, stderr=stream,
                           env=env, cwd=ROOT, text=True, timeout=120)
    lines = err.read_text().splitlines()
    assert r.returncode == 0, lines
    logged = [t for t in lines if t.startswith("<")]
    assert any(t.startswith("<6>tracking 3 cameras") for t in logged), lines
    assert any(t.startswith("<4>serial:") and "cannot open" in t for t in logged), lines
    assert all(t.startswith("<") for t in lines), lines  # progress lines too (info)
    assert any(t.startswith("<6>mocapd: 60/60") for t in lines)


def test_table_rows_stay_whole_off_a_terminal():
    out = io.StringIO()
    rows = [["a body with a long name " * 4, 1, 0.25, float("nan")], ["b", 22, 1234.5, 1e-5]]
    print_table(rows, ["body", "id", "error_mm", "rate"], file=out)
    lines = out.getvalue().splitlines()
    assert len(lines) == 4  # header, rule, two rows: nothing folded at 80 columns
    assert lines[0].split() == ["body", "id", "error_mm", "rate"]
    assert lines[2].split()[-3:] == ["1", "0.250", "-"]
    assert lines[3].split() == ["b", "22", "1234.5", "1e-05"]
    # numbers right-aligned: the ids end in the same column
    assert lines[2].index(" 1 ") + 2 == lines[3].index("22") + 2


def test_progress_off_a_terminal_prints_lines_and_a_last_one():
    out = io.StringIO()
    p = Progress("mocapd", 100, every_s=0.0, stream=out)
    p.update(40)
    p.finish("done")
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("mocapd: 40/100 (40%)")
    assert lines[-1].startswith("mocapd: 40/100 (40%)") and lines[-1].endswith("done")
