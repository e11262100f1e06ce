"""Shared test helpers: run a command line in-process and capture its exit code and output."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest

# One BLAS thread: on a small shared machine (CI has 2 cores) a multi-threaded BLAS
# oversubscribes the cores and small matrix products get 100x slower. Set before numpy
# loads its BLAS (nothing above imports numpy); .ci/run sets the same.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# Bytecode: machines like CI's set PYTHONDONTWRITEBYTECODE, so each of a run's child
# processes (a mocapd, a node, a command line: well over a hundred) would compile the
# project's 40,000 lines again, about half a second of CPU each. The tests keep it in a
# cache outside the tree instead (PYTHONPYCACHEPREFIX: the tree stays as it was), this
# process and its children alike; Python recompiles whatever source is newer.
if os.environ.get("PYTHONDONTWRITEBYTECODE") and not os.environ.get("PYTHONPYCACHEPREFIX"):
    _prefix = str(Path(tempfile.gettempdir()) / f"calibkit-tests-pycache-{os.getuid()}")
    os.environ["PYTHONPYCACHEPREFIX"] = _prefix
    del os.environ["PYTHONDONTWRITEBYTECODE"]
    sys.pycache_prefix, sys.dont_write_bytecode = _prefix, False


ROOT = Path(__file__).resolve().parents[1]
# test modules that start mocapd and time what it does live
LIVE_DAEMON_MODULES = {"test_daemon_e2e", "test_daemon_pipeline", "test_live_label",
                       "test_mavlink", "test_natnet", "test_natnet_protocol", "test_vrpn",
                       "test_logs", "test_daemon_config", "test_examples", "test_nodes",
                       "test_nodes_link"}


ALL = "every test of the module"
# The slow tests: `python3 -m pytest -m "not slow"` leaves them out (the fast set, under a
# minute on a quiet 2-core machine); CI runs everything. Each took over about a second in
# a full run (docs/testing.md has the figures): live daemons and nodes, a browser, child
# processes, fuzzing, whole calibrations and labellings, compiling. Kept here, beside the
# live modules above, rather than as a decorator on each test: one table to read and keep
# up, and a name in it that its module no longer defines fails the run.
SLOW: dict[str, str | set[str]] = {
    # whole modules: compiling, the demo, namespaces, a browser, a live daemon per test
    "test_kernels_cache": ALL, "test_demo": ALL, "test_nodes_link": ALL,
    "test_view_browser": ALL, "test_view_detection": ALL, "test_reload": ALL,
    "test_daemon_e2e": {"test_live_daemon_outputs_control_reload_and_stop",
                        "test_camera_dropout_and_a_consumer_that_stops_reading",
                        "test_fast_sim_run_writes_pose_errors", "test_install_unit",
                        "test_replay_a_recording", "test_live_cameras_with_a_missing_plugin",
                        "test_greedy_multiplexer_live",
                        "test_greedy_multiplexer_with_unsynchronised_cameras",
                        "test_late_opener_and_a_reconnecting_camera_live",
                        "test_sim_without_scoring_runs_the_daemon_alone"},
    "test_natnet": {"test_natnet_clients_unicast_and_multicast_join_and_leave",
                    "test_motioncapture_natnet_multicast_with_a_late_second_client",
                    "test_motioncapture_natnet_unicast",
                    "test_mocapd_serves_natnet_poses_matching_the_simulator",
                    "test_a_reloaded_server_takes_over_the_port_and_the_clients",
                    "test_a_reload_keeps_unicast_clients_that_send_no_keep_alives"},
    "test_natnet_protocol": {"test_optitrack_sample_client_unicast_against_mocapd",
                             "test_optitrack_sample_client_multicast_against_mocapd"},
    "test_live_label": {"test_stage_labels_the_person_inline_with_ghosts_and_gaps",
                        "test_stage_starts_on_a_thread_and_catches_up",
                        "test_stage_start_waits_for_a_busy_worker",
                        "test_stage_starts_from_the_set_alone_and_repairs_itself_on_another_subject",
                        "test_mocapd_publishes_named_markers_over_udp_and_natnet_and_reloads_the_set"},
    "test_nodes": {"test_a_simulated_node_serves_its_cameras_from_one_thread_on_time",
                   "test_node_with_a_bad_endpoint_exits_with_one_line",
                   "test_two_nodes_feed_one_daemon_clocks_estimated_and_bodies_tracked",
                   "test_a_killed_node_is_dropped_and_its_cameras_rejoin_within_2_s_of_its_restart",
                   "test_poses_go_out_over_zenoh_to_a_subscriber_on_another_session",
                   "test_a_node_serving_a_camera_the_daemon_does_not_take_is_warned_about"},
    "test_robot_example": {"test_goto_point_reaches_ten_targets_within_2_cm_of_the_truth",
                           "test_goto_point_c_decodes_the_serial_line_as_python_does_and_drives",
                           "test_sysid_estimates_the_simulated_robots_delay_and_lag",
                           "test_examples_refuse_bad_input_in_one_line"},
    "test_examples": {"test_head_tracking_against_the_simulated_daemon",
                      "test_head_tracking_refuses_a_bad_screen",
                      "test_paint3d_against_the_simulated_daemon",
                      "test_paint3d_refuses_bad_input"},
    "test_mavlink": {
        "test_a_uart_autopilot_hears_heartbeats_gapless_sequences_timesync_and_the_origin",
        "test_udp_both_ways_with_a_mavutil_autopilot",
        "test_mocapd_start_serves_an_autopilot_over_udp_and_status_shows_it"},
    "test_vrpn": {"test_raw_clients_over_tcp_and_connect_back_with_pings",
                  "test_motioncapture_vrpn_clients_join_and_leave",
                  "test_a_client_that_stops_reading_is_dropped_and_the_others_go_on",
                  "test_mocapd_vrpn_flag_serves_poses_matching_the_simulator",
                  "test_a_reload_keeps_the_clients_connected"},
    "test_logs": {"test_mocapd_start_under_the_journal"},
    "test_daemon_pipeline": {"test_rigid_body_from_live_markers"},
    "test_realtime": {"test_a_live_run_tracks_real_time_reports_its_stages_and_returns_normal",
                      "test_a_live_run_keeps_its_start_up_out_of_the_collector_and_gives_it_back"},
    "test_soak_short": {"test_daemon_through_a_reload_and_a_recording_keeps_its_figures_bounded"},
    "test_fuzz_files": {"test_any_json_records_give_observations_or_one_user_error",
                        "test_any_csv_bytes_give_observations_or_one_user_error",
                        "test_a_damaged_c3d_gives_a_take_or_one_user_error",
                        "test_any_configuration_values_give_a_config_or_one_user_error"},
    "test_fuzz_natnet": {
        "test_every_message_kind_with_any_payload_gets_a_well_formed_answer_or_none",
        "test_every_command_with_random_arguments",
        "test_junk_on_a_live_command_port_logs_one_line_per_kind_and_frames_keep_coming"},
    "test_fuzz_nodes": {"test_no_payload_escapes_a_callback"},
    "test_fuzz_view": {"test_malformed_connections_to_a_running_view_log_one_line_per_kind",
                       "test_detection_values_from_the_page_are_checked"},
    "test_fuzz_mavlink": {"test_any_bytes_from_the_autopilot_are_parsed_without_raising"},
    "test_label_subjects": {"test_a_correct_start_never_ends_worse_on_another_body"},
    "test_cli_startup": {"test_help_everywhere_imports_nothing_heavy"},
    "test_detect": {"test_colour_images_and_16_bit_images_are_converted"},
    "test_extrinsic_cli": {"test_sim_starts_from_the_intrinsics_file"},
}


def _slow_names(module) -> set[str] | None:
    entry = SLOW.get(module.__name__.rsplit(".", 1)[-1])
    if entry == ALL:
        return {n for n in vars(module) if n.startswith("test_")}
    return entry


@pytest.hookimpl(tryfirst=True)  # before -m reads the marks
def pytest_collection_modifyitems(config, items):
    """Marks the tests SLOW names; a name its module does not define is an error."""
    checked = set()
    for item in items:
        module = getattr(item, "module", None)
        names = None if module is None else _slow_names(module)
        if names is None:
            continue
        if module not in checked:
            checked.add(module)
            gone = sorted(n for n in names if not hasattr(module, n))
            if gone:
                raise pytest.UsageError(f"tests/conftest.py SLOW names tests "
                                        f"{module.__name__} does not define: {', '.join(gone)}")
        if getattr(item, "originalname", item.name) in names:
            item.add_marker(pytest.mark.slow)


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
