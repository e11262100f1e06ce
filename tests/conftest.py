"""Shared test helpers: run a command line in-process and capture its exit code and output."""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import tempfile
import threading
import warnings
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


ALL = "every test of the module"
# The slow tests: `python3 -m pytest -m "not slow"` leaves them out (the fast set, for a
# developer at work); CI runs everything. Live daemons and nodes, a browser, example
# programs, hundreds of fuzzing examples, whole labellings, compiling: the tests that took
# 3 s or more (about half a second on a quiet machine) in a full run at load 10-35 on
# 2026-11-27 (docs/testing.md; `-m "not slow" --durations=20` shows what else belongs
# here). Kept in one table beside the live modules above rather than a decorator on each
# of some 290 tests: one place to read and keep up; a name in it that its module no longer
# defines is warned about. Newer modules mark their own with @pytest.mark.slow.
SLOW: dict[str, str | set[str]] = {
    # whole modules: compiling, the demo, namespaces, a browser, a daemon per test
    "test_demo": ALL, "test_kernels_cache": ALL, "test_nodes_link": ALL, "test_reload": ALL,
    "test_view_browser": ALL, "test_view_detection": ALL,
    "test_view_contrast": ALL,
    "test_label_recording": ALL,
    "test_wand_dots": ALL,
    "test_wand_views": ALL,
    "test_boundary": {
        "test_importing_every_estimating_module_loads_no_simulator"},
    "test_cli_startup": {
        "test_help_everywhere_imports_nothing_heavy"},
    "test_daemon_e2e": {
        "test_camera_dropout_and_a_consumer_that_stops_reading",
        "test_fast_sim_run_writes_pose_errors",
        "test_greedy_multiplexer",
        "test_greedy_multiplexer_with_unsynchronised_cameras",
        "test_install_unit",
        "test_late_opener_and_a_reconnecting_camera_live",
        "test_live_cameras_with_a_missing_plugin",
        "test_live_daemon_outputs_control_reload_and_stop",
        "test_replay_a_recording",
        "test_sim_without_scoring_runs_the_daemon_alone"},
    "test_daemon_pipeline": {
        "test_rigid_body_from_live_markers"},
    "test_detect": {
        "test_colour_images_and_16_bit_images_are_converted",
        "test_compiled_path_equals_the_numpy_reference_on_random_scenes"},
    "test_easywand": {
        "test_wand_from_xypts_end_to_end"},
    "test_examples": {
        "test_head_tracking_against_the_simulated_daemon",
        "test_head_tracking_refuses_a_bad_screen",
        "test_paint3d_against_the_simulated_daemon",
        "test_paint3d_refuses_bad_input"},
    "test_extrinsic": {
        "test_a_camera_that_sees_nothing_is_named_and_the_others_are_calibrated",
        "test_plane_dots_hold_the_world_frame_in_a_wand_bundle",
        "test_plane_observations_for_the_bundle_and_the_floor",
        "test_poses_meet_the_targets_with_tape_error_and_centroid_noise",
        "test_rendered_capture_identifies_dots_and_places_cameras",
        "test_the_dots_recover_the_table_height_from_a_bad_tape"},
    "test_extrinsic_cli": {
        "test_live_path_with_a_stand_in_projector_and_cameras",
        "test_rendered_sim_runs_detection_end_to_end",
        "test_sim_starts_from_the_intrinsics_file",
        "test_sim_without_a_table_warns_and_still_calibrates",
        "test_sim_writes_the_rig_truth_and_plane_observations"},
    "test_fast_pairing": {
        "test_the_fast_daemon_run_goes_through_the_multiplexer"},
    "test_fuzz_files": {
        "test_a_bad_csv_cell_names_its_line_and_column",
        "test_a_damaged_c3d_gives_a_take_or_one_user_error",
        "test_a_malformed_record_names_the_file_and_its_line",
        "test_any_configuration_values_give_a_config_or_one_user_error",
        "test_any_csv_bytes_give_observations_or_one_user_error",
        "test_any_json_records_give_observations_or_one_user_error"},
    "test_fuzz_mavlink": {
        "test_any_bytes_from_the_autopilot_are_parsed_without_raising"},
    "test_fuzz_natnet": {
        "test_every_command_with_random_arguments",
        "test_every_message_kind_with_any_payload_gets_a_well_formed_answer_or_none",
        "test_junk_on_a_live_command_port_logs_one_line_per_kind_and_frames_keep_coming"},
    "test_fuzz_nodes": {
        "test_no_payload_escapes_a_callback"},
    "test_fuzz_view": {
        "test_detection_values_from_the_page_are_checked",
        "test_library_records_become_one_line_per_kind",
        "test_malformed_connections_to_a_running_view_log_one_line_per_kind"},
    "test_intrinsic": {
        "test_bias_correction_removes_large_dot_error",
        "test_display_mode_runs_with_a_monitor_and_camera",
        "test_every_camera_of_a_simulated_rig",
        "test_intrinsic_sim_command",
        "test_monitor_out_of_view_is_a_clear_error",
        "test_monitor_partly_out_of_view_reaches_the_corners",
        "test_projected_dots_agree_with_the_rendered_capture",
        "test_raster_scan_capture",
        "test_reported_std_matches_the_actual_errors",
        "test_solve_against_truth"},
    "test_label": {
        "test_cli_label_by_shipped_name_reports_a_marker_stored_twice",
        "test_cli_label_from_labelled_start_frames",
        "test_forearm_hidden_whole_is_found_again",
        "test_gap_free_from_the_template_alone",
        "test_hard_occlusion_patterns",
        "test_hidden_spans_and_ghosts",
        "test_kernels_match_their_numpy_twins",
        "test_markers_stored_twice_are_labelled_as_one",
        "test_modules_found_again_after_long_occlusions",
        "test_other_subjects_marker_set_from_the_template_alone",
        "test_other_subjects_marker_set_with_labelled_start_frames",
        "test_start_from_the_marker_set_alone_with_occlusions",
        "test_verification_repairs_a_wrong_start",
        "test_wrist_markers_taken_for_each_other_are_set_right"},
    "test_label_extras": {  # whole labellings of a subject carrying extra markers (2-6 s)
        "test_the_set_alone_leaves_markers_it_lacks_unlabelled"},
    "test_label_relearn": {
        "test_a_labelled_start_keeps_a_sliding_marker_the_set_alone_keeps"},
    "test_label_start": {
        "test_cmu_set_starts_right_on_a_walker_of_another_size",
        "test_set_learned_on_another_subject_starts_right",
        "test_window_start_with_hidden_markers_and_ghosts"},
    "test_label_subjects": {
        "test_a_correct_start_never_ends_worse_on_another_body",
        "test_a_leg_turned_along_its_chain_is_put_right",
        "test_a_scrambled_start_is_put_right_from_the_frames_before_it",
        "test_another_body_from_the_set_alone"},
    "test_supervise": {
        "test_every_kind_of_thread_restarts_after_an_injected_exception"},
    "test_supervise_more": {
        "test_a_killed_view_process_is_restarted_and_status_says_so"},
    "test_label_verify": {
        "test_verification_brings_in_points_tracking_left_out"},
    "test_layer_imports": {
        "test_calibration_and_vision_never_import_the_display",
        "test_every_daemon_package_has_a_layer",
        "test_importing_the_calibration_modules_loads_no_display",
        "test_importing_the_core_and_the_cameras_loads_no_upper_layer",
        "test_only_the_entry_point_imports_the_command_handlers",
        "test_our_packages_have_no_import_cycles",
        "test_the_core_and_the_cameras_import_no_upper_layer",
        "test_the_daemon_never_imports_calibkit_commands",
        "test_the_daemon_packages_import_only_lower_layers"},
    "test_live_label": {
        "test_mocapd_publishes_named_markers_over_udp_and_natnet_and_reloads_the_set",
        "test_stage_labels_the_person_inline_with_ghosts_and_gaps",
        "test_stage_searches_again_after_losing_the_subject_and_survives_a_failure",
        "test_stage_start_waits_for_a_busy_worker",
        "test_stage_starts_from_the_set_alone_and_repairs_itself_on_another_subject",
        "test_stage_starts_on_a_thread_and_catches_up",
        "test_the_shipped_person_set_is_what_sim_person_set_learns"},
    "test_logs": {
        "test_mocapd_start_under_the_journal"},
    "test_markerset": {
        "test_cli_learn",
        "test_cli_markerset_check",
        "test_distances_match_the_take",
        "test_segments_group_markers_that_keep_their_shape"},
    "test_mavlink": {
        "test_a_rate_that_does_not_fit_refuses_to_start",
        "test_a_uart_autopilot_hears_heartbeats_gapless_sequences_timesync_and_the_origin",
        "test_mocapd_start_serves_an_autopilot_over_udp_and_status_shows_it",
        "test_udp_both_ways_with_a_mavutil_autopilot"},
    "test_mcap": {
        "test_track_to_mcap_holds_the_poses_and_markers"},
    "test_multiplexer": {
        "test_clocks_drifting_50_ppm_for_two_minutes_stay_paired"},
    "test_natnet": {
        "test_a_reload_keeps_unicast_clients_that_send_no_keep_alives",
        "test_a_reloaded_server_takes_over_the_port_and_the_clients",
        "test_any_datagram_on_the_command_port_gets_an_answer_or_none",
        "test_mocapd_serves_natnet_poses_matching_the_simulator",
        "test_motioncapture_natnet_multicast_with_a_late_second_client",
        "test_motioncapture_natnet_unicast",
        "test_natnet_clients_unicast_and_multicast_join_and_leave"},
    "test_natnet_protocol": {
        "test_optitrack_sample_client_multicast_against_mocapd",
        "test_optitrack_sample_client_unicast_against_mocapd"},
    "test_nodes": {
        "test_a_killed_node_is_dropped_and_its_cameras_rejoin_within_2_s_of_its_restart",
        "test_a_node_serving_a_camera_the_daemon_does_not_take_is_warned_about",
        "test_a_simulated_node_serves_its_cameras_from_one_thread_on_time",
        "test_node_with_a_bad_endpoint_exits_with_one_line",
        "test_poses_go_out_over_zenoh_to_a_subscriber_on_another_session",
        "test_two_nodes_feed_one_daemon_clocks_estimated_and_bodies_tracked"},
    "test_points_csv": {
        "test_label_warns_about_bad_rows_and_strict_refuses"},
    "test_publish": {
        "test_cobs_round_trip_has_no_zero"},
    "test_realtime": {
        "test_a_live_run_keeps_its_start_up_out_of_the_collector_and_gives_it_back",
        "test_a_live_run_tracks_real_time_reports_its_stages_and_returns_normal"},
    "test_rigformats": {
        "test_any_damage_reads_or_gives_one_line_never_a_traceback"},
    "test_robot_example": {
        "test_examples_refuse_bad_input_in_one_line",
        "test_goto_point_c_decodes_the_serial_line_as_python_does_and_drives",
        "test_goto_point_reaches_five_targets_within_2_cm_of_the_truth",
        "test_sysid_estimates_the_simulated_robots_delay_and_lag",
        "test_sysid_recovers_the_delay_and_time_constant_of_a_simulated_response",
        "test_the_cameras_see_the_robot_where_its_truth_says"},
    "test_skeleton": {
        "test_cli_skeleton"},
    "test_soak_short": {
        "test_daemon_through_a_reload_and_a_recording_keeps_its_figures_bounded",
        "test_stats_keep_a_bounded_sample_whose_percentiles_are_the_runs"},
    "test_track": {
        "test_command_output_is_the_rigid_tracker_called_frame_by_frame",
        "test_definition_4mm_off_is_fitted_to_the_take",
        "test_motive_1_0_take_four_bodies_one_definition_off",
        "test_simulated_capture_poses_against_the_truth"},
    "test_tracker": {
        "test_compiled_kernel_matches_the_numpy_reference",
        "test_markers_of_two_bodies_crossing_closer_than_the_gate_keep_their_identities",
        "test_the_daemon_tracks_with_a_calibrated_rig_and_bodies_defined_live"},
    "test_trajectory": {
        "test_the_command_scores_a_flight_and_writes_its_report"},
    "test_view_coverage": {
        "test_intrinsic_display_view_shows_the_views_before_each_prompt",
        "test_intrinsic_views_page_shows_each_views_dots_and_the_coverage",
        "test_the_page_fills_in_as_the_wand_is_waved"},
    "test_view_replay": {
        "test_the_slider_draws_the_chosen_frame"},
    "test_view_report": {
        "test_extrinsic_report_renders_with_the_json_figures",
        "test_intrinsic_report_renders_with_the_json_figures",
        "test_report_is_written_beside_the_rig_and_holds_everything",
        "test_report_renders_in_a_browser_with_the_json_figures"},
    "test_vrpn": {
        "test_a_client_that_stops_reading_is_dropped_and_the_others_go_on",
        "test_a_reload_keeps_the_clients_connected",
        "test_hostile_datagrams_never_stop_the_server_nor_send_it_elsewhere",
        "test_mocapd_vrpn_flag_serves_poses_matching_the_simulator",
        "test_motioncapture_vrpn_clients_join_and_leave",
        "test_raw_clients_over_tcp_and_connect_back_with_pings"},
    "test_wand": {
        "test_grade_sees_wrong_intrinsics_that_the_pixels_hide",
        "test_held_out_figures_match_the_solved_ones",
        "test_initial_poses_from_nothing",
        "test_one_marker_wand_needs_initial_poses_for_its_scale",
        "test_two_marker_wand_with_initial_poses_and_from_nothing"},
    "test_wand_cli": {
        "test_a_camera_that_never_sees_the_wand",
        "test_live_capture_from_camera_image_folders",
        "test_wand_bad_input_is_one_clear_line",
        "test_wand_from_csv_with_intrinsics",
        "test_wand_sim_end_to_end",
        "test_wand_sim_starts_from_the_intrinsics_file",
        "test_wand_with_an_lframe_recording_sets_the_floor"},
    "test_wand_pairing": {
        "test_dropped_frames_solve_as_well_as_none_dropped",
        "test_old_recordings_numbered_by_instant_are_read_as_they_are",
        "test_recordings_keep_each_cameras_frames_and_pair_the_same",
        "test_triangulate_pairs_a_recording_whose_cameras_count_their_own_frames"},
    "test_wand_small": {
        "test_an_lframe_sets_the_scale_of_a_wand_of_unknown_length",
        "test_cli_small_capture_of_unknown_length",
        "test_degenerate_captures_solve_or_say_why_in_one_line",
        "test_every_figure_is_a_number_or_says_why_not",
        "test_exact_intrinsics_without_uncertainties_are_kept",
        "test_held_intrinsics_off_show_as_structure_on_a_small_capture",
        "test_nan_rows_are_left_out_not_solved",
        "test_refined_intrinsics_the_file_was_overconfident_about_are_not_excellent",
        "test_small_captures_start_from_pairwise_geometry_and_solve",
        "test_unknown_length_is_the_known_solve_scaled",
        "test_wrong_intrinsics_without_uncertainties_are_refined"},
    "test_zenoh_auth": {
        "test_only_listed_users_deliver_on_loopback"},
    "test_multiplexer_behind": {
        "test_the_set_deadline_follows_the_waits_complete_sets_took_within_its_bounds"},
    "test_wand_shape": {
        "test_prediction_matches_the_error_against_the_truth",
        "test_report_says_what_the_capture_cannot_rule_out"},
    "test_soak_stop": {
        "test_a_run_to_its_end_prints_and_writes_its_figures",
        "test_sigterm_leaves_the_recording_whole_and_the_figures_written"},
    "test_assignment": {
        "test_labelling_does_not_load_scipy_optimize"},
    "test_camera": {
        "test_undistort_matches_opencv_over_whole_image"},
    "test_board": {
        "test_real_chessboard_matches_qualisys"},
    "test_bundle": {
        "test_outliers_are_dropped_and_the_solve_holds"},
}


def _slow_names(module) -> set[str] | None:
    entry = SLOW.get(module.__name__.rsplit(".", 1)[-1])
    if entry == ALL:
        return {n for n in vars(module) if n.startswith("test_")}
    return entry


@pytest.hookimpl(tryfirst=True)  # before -m reads the marks
def pytest_collection_modifyitems(config, items):
    """Marks the tests SLOW names (a name its module does not define, a test renamed or
    removed, is a warning in the run's summary, not an error that would stop everyone's
    runs for a table entry), then puts the LONGEST_FIRST modules first."""
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
                warnings.warn(pytest.PytestConfigWarning(
                    f"tests/conftest.py SLOW names tests {module.__name__} does not define: "
                    f"{', '.join(gone)}"), stacklevel=1)
        if getattr(item, "originalname", item.name) in names:
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}  # stable: modules stay whole

    def order(item) -> int:
        stem = Path(str(item.fspath)).stem
        if stem in RUN_WHILE_KERNELS_BUILD and item.get_closest_marker("kernels"):
            return rank["test_robot_example"]  # waits for the build: after those that do not
        return rank.get(stem, len(rank))

    items.sort(key=order)


# The longest modules first, the rest in their order: on two workers (-n 2 --dist loadfile)
# a long module handed out last leaves one worker running it alone at the end; longest
# first keeps the two ending together. xdist hands modules out in this order only with
# --no-loadscope-reorder (pyproject.toml's addopts): by default it sorts them by their
# number of tests, which handed the namespaces, the kernel cache and the browser last.
# Ordered by each module's wall time in a whole run (docs/testing.md, 2026-11-27 19:26 at
# load 0.4-19, mean 9; seconds there): the robot's live drives 230, the labeller on other subjects
# 175, namespaces and node clocks over links 130, ...; below about 15 s the order matters
# little, the small modules fill the end. The labeller's modules come first whatever
# their length: they run while the session's kernels build (RUN_WHILE_KERNELS_BUILD), and
# their tests are shared a test at a time, so their place does not unbalance the end.
LONGEST_FIRST = (
    "test_label_subjects", "test_label", "test_label_verify", "test_label_start",
    "test_robot_example", "test_nodes_link",
    "test_kernels_cache", "test_nodes", "test_live_label", "test_daemon_e2e",
    "test_view_browser", "test_bench_nodes_config", "test_natnet_protocol", "test_demo",
    "test_wand_cli",
    "test_view_coverage", "test_fuzz_files",
    "test_wand_pairing", "test_extrinsic", "test_view_report", "test_wand", "test_wand_small",
    "test_layer_imports", "test_intrinsic", "test_extrinsic_cli", "test_fuzz_view",
    "test_view_replay", "test_examples", "test_wand_dots", "test_boundary",
    "test_view_detection", "test_wand_shape", "test_vrpn", "test_mavlink",
    "test_view_contrast", "test_natnet", "test_fuzz_nodes", "test_multiplexer", "test_track",
    "test_wand_views", "test_tracker")



# Modules whose tests are handed out one at a time (every other module goes whole to one
# worker, for its module fixtures: a daemon, a browser, namespaces): long, bound by the
# CPU, with no live daemon, browser, port or shared file, and only cheap module fixtures
# (a marker set, a take read from a file) that each worker then builds for itself. Whole,
# the labeller on other subjects (9 tests, 3 minutes at load 10) kept one worker busy
# while the other ran out of work; one test at a time, both share it.
SHARED_BY_TESTS = {"test_label_subjects", "test_label", "test_label_start", "test_label_verify",
                   "test_fuzz_files", "test_wand_cli", "test_extrinsic", "test_intrinsic"}


@pytest.hookimpl(optionalhook=True)  # a hook of xdist's: `-p no:xdist` runs without it
def pytest_xdist_make_scheduler(config, log):
    """`--dist loadfile` as xdist does it, except for the SHARED_BY_TESTS modules, whose
    tests are units of their own; any other --dist is left to xdist."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class ModulesWholeButShared(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if Path(nodeid.split("::", 1)[0]).stem in SHARED_BY_TESTS:
                return nodeid
            return super()._split_scope(nodeid)

    return ModulesWholeButShared(config, log)


# Modules whose tests need no kernel compiled beforehand (the labeller's, offline, in the
# test's own process): they run while the kernels build, first in LONGEST_FIRST, but for
# their tests marked `kernels` (a Labeller's compiled kernels, which would compile in the
# test's process). Every other test waits for the build, as a daemon, a node or an example
# started by one would otherwise compile for a minute inside its first seconds.
RUN_WHILE_KERNELS_BUILD = {"test_label_subjects", "test_label", "test_label_start",
                           "test_label_verify"}
_KERNEL_BUILD: dict = {}  # this process's build: {"proc", "log", "done", "ready"}


def _kernel_build_files() -> tuple[Path, Path]:
    """The lock the build holds while it runs, and the file it leaves when it succeeded
    (per run: xdist's workers share the run's id)."""
    tmp = Path(tempfile.gettempdir())
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID", str(os.getpid()))
    return (tmp / f"calibkit-tests-kernels-{os.getuid()}.lock",
            tmp / f"calibkit-tests-kernels-{os.getuid()}-{run}.done")


BUILD_IN_CHILD = """
import ctypes, os, signal, sys
from pathlib import Path
signal.signal(signal.SIGINT, signal.default_int_handler)
try:
    ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: ends with the worker
except (OSError, AttributeError):
    pass
if os.getppid() != int(sys.argv[2]):  # the worker died before that
    sys.exit(1)
from daemon.commands.kernels_cmd import build_kernels
build_kernels(lambda _: None)
Path(sys.argv[1]).write_text("ok")
"""


@pytest.fixture(scope="session", autouse=True)
def _daemon_kernels_building(request):
    """Start compiling mocapd's kernels into the on-disk cache (`mocapd build-kernels`, as
    a user does after installing) as the run starts, in the background: on a fresh
    checkout it takes a minute, which the labeller's tests use instead of waiting. One
    build for the whole run: the first worker to take the lock builds, and the build
    process holds the lock until it ends (the other worker's tests wait on it)."""
    slow = {Path(str(item.fspath)).stem for item in request.session.items
            if item.get_closest_marker("slow") is not None}  # the fast set runs none live
    if not slow - RUN_WHILE_KERNELS_BUILD:
        _KERNEL_BUILD["ready"] = True
        yield
        return
    lock, done = _kernel_build_files()
    held = open(lock, "w")
    try:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:  # another worker builds: its lock tells when it is done
        held.close()
    else:
        log = tempfile.TemporaryFile()
        # the child inherits the locked file and keeps the lock until it exits; Ctrl-C
        # stops it even where the run was started with SIGINT ignored (a background job),
        # and it ends when the worker dies (a run killed without its teardown)
        _KERNEL_BUILD.update(done=done, log=log, proc=subprocess.Popen(
            [sys.executable, "-c", BUILD_IN_CHILD, str(done), str(os.getpid())], cwd=ROOT,
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            pass_fds=(held.fileno(),), env=dict(os.environ, PYTHONPATH=str(ROOT))))
        held.close()
    yield
    proc = _KERNEL_BUILD.get("proc")
    if proc is not None:
        if proc.poll() is None:  # no test of this worker waited: the run ends anyway
            proc.terminate()
            proc.wait(timeout=60)
        _KERNEL_BUILD["done"].unlink(missing_ok=True)


@pytest.fixture(autouse=True)
def _daemon_kernels_compiled(request, _daemon_kernels_building):
    """Every test but the labeller's waits for the build (once per process): a live test
    timing its first packets would measure the compiler instead of the daemon."""
    if _KERNEL_BUILD.get("ready") or (
            Path(str(request.node.fspath)).stem in RUN_WHILE_KERNELS_BUILD
            and request.node.get_closest_marker("kernels") is None):
        return
    proc = _KERNEL_BUILD.get("proc")
    if proc is not None:  # this process started it
        code = proc.wait(timeout=900)
        if code != 0:
            _KERNEL_BUILD["log"].seek(0)
            pytest.fail(f"mocapd build-kernels failed ({code}): "
                        f"{_KERNEL_BUILD['log'].read()[-2000:].decode(errors='replace')}")
    else:  # another worker builds, or built: wait for its lock, then see that it succeeded
        lock, done = _kernel_build_files()
        with open(lock, "w") as held:
            fcntl.flock(held, fcntl.LOCK_EX)
            if not done.exists():  # it failed or never ran: build here (cached: seconds)
                subprocess.run([sys.executable, "-m", "daemon.cli", "build-kernels",
                                "--quiet"], cwd=ROOT, capture_output=True, timeout=900,
                               check=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    _KERNEL_BUILD["ready"] = True


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
