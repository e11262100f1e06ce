"""Shared test helpers: run a command line in-process and capture its exit code and output."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest

# One BLAS thread: on a small shared machine (CI has 2 cores) a multi-threaded BLAS
# oversubscribes the cores and small matrix products get 100x slower. Set before numpy
# loads its BLAS (nothing above imports numpy); .ci/run sets the same.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


ROOT = Path(__file__).resolve().parents[1]
# test modules that start mocapd and time what it does live
LIVE_DAEMON_MODULES = {"test_daemon_e2e", "test_daemon_pipeline", "test_live_label",
                       "test_mavlink", "test_natnet", "test_natnet_protocol", "test_vrpn",
                       "test_logs", "test_daemon_config", "test_examples", "test_nodes",
                       "test_nodes_link"}


@pytest.fixture(scope="session", autouse=True)
def _daemon_kernels_compiled(request):
    """Compile mocapd's kernels into the on-disk cache once (`mocapd build-kernels`, as a
    user does after installing), before tests that run the daemon live: on a fresh
    checkout the first start would compile for tens of seconds, and a live test timing its
    first packets would measure the compiler instead of the daemon."""
    modules = {Path(str(item.fspath)).stem for item in request.session.items}
    if modules & LIVE_DAEMON_MODULES:
        subprocess.run([sys.executable, "-m", "daemon.cli", "build-kernels", "--quiet"],
                       cwd=ROOT, capture_output=True, timeout=900, check=True,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))


@pytest.fixture(autouse=True)
def _ctrl_c_stops_the_run(monkeypatch):
    """Ctrl-C stops the whole run, also while a test runs `mocapd start` in-process: the
    daemon takes SIGINT for itself (a clean stop of its run), which would end that one test
    and let pytest go on to the next. Every SIGINT handler installed during a test is wrapped
    so that it also notes the signal, and the test's teardown turns a noted one into the
    KeyboardInterrupt pytest stops on."""
    noted = []
    install = signal.signal

    def noting(sig, handler):
        if (sig == signal.SIGINT and callable(handler)
                and threading.current_thread() is threading.main_thread()):
            inner = handler

            def handler(signum, frame):
                noted.append(signum)
                inner(signum, frame)
        return install(sig, handler)

    monkeypatch.setattr(signal, "signal", noting)
    yield
    if noted:
        raise KeyboardInterrupt


@pytest.fixture(autouse=True)
def _mocapd_logger_restored():
    """An in-process `mocapd start` points the "mocapd" logger at that test's captured
    stderr and stops it propagating (daemon.process.logs.setup_logging): put it back after each
    test, so later tests' caplog sees the daemon's records and nothing writes to a closed
    capture."""
    import logging

    logger = logging.getLogger("mocapd")
    saved = (list(logger.handlers), logger.propagate, logger.level)
    yield
    logger.handlers[:], logger.propagate, logger.level = saved[0], saved[1], saved[2]


@dataclass
class CliResult:
    code: int
    out: str
    err: str


def _run(app_module: str, prog: str, capsys, args) -> CliResult:
    import importlib

    from calibkit.clitools import run_app

    app = importlib.import_module(app_module).app
    old = sys.argv
    sys.argv = [prog, *(str(a) for a in args)]
    code = 0
    try:
        run_app(app, prog)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = old
    captured = capsys.readouterr()
    return CliResult(code, captured.out, captured.err)


@pytest.fixture
def calibkit_cli(capsys):
    """calibkit_cli('rig', 'export', ...) -> CliResult(code, out, err), as from the shell."""
    return lambda *args: _run("calibkit.cli", "calibkit", capsys, args)


@pytest.fixture
def mocapd_cli(capsys):
    return lambda *args: _run("daemon.cli", "mocapd", capsys, args)


@pytest.fixture
def start_refused(tmp_path, mocapd_cli):
    """`mocapd start --config PATH --sim` that must refuse: exit code 2, one line on
    stderr, nothing opened (no runtime directory). Returns that line."""
    def run(path) -> str:
        runtime = tmp_path / "rt"
        r = mocapd_cli("start", "--config", path, "--sim", "--frames", 5, "--runtime-dir",
                       runtime)
        assert r.code == 2
        lines = r.err.strip().splitlines()
        assert len(lines) == 1, r.err
        assert not runtime.exists()  # nothing opened before the check
        return lines[0]
    return run


@pytest.fixture
def natnet_listener():
    """natnet_listener(command_port, data_port=command_port + 1, multicast=False,
    timeout_s=3.0) -> (client, frames, descriptions): the real NatNet client library
    (`natnet` package) connected to a server on 127.0.0.1, collecting what it receives;
    call client.shutdown() when done."""
    import natnet

    def connect(command_port, data_port=None, multicast=False, timeout_s=3.0):
        c = natnet.NatNetClient(server_ip_address="127.0.0.1", local_ip_address="127.0.0.1",
                                command_port=command_port,
                                data_port=command_port + 1 if data_port is None else data_port,
                                use_multicast=multicast)
        frames, descs = [], []
        c.on_data_frame_received_event.handlers.append(frames.append)
        c.on_data_description_received_event.handlers.append(descs.append)
        c.connect(timeout=timeout_s)
        c.request_modeldef()
        c.run_async()
        return c, frames, descs

    return connect
