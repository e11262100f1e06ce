"""benchmarks/bench_nodes.py's configurations: the camera split, the refusal of a bad one,
and a short sweep that runs a 2-node configuration (on loopback, and in network namespaces
where the machine can make them) and leaves nothing behind. No speed is asserted: the
figures are the benchmark's business."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_nodes  # noqa: E402 - a benchmark script, imported from its folder
import nodes_netns  # noqa: E402
import nodes_sweep  # noqa: E402

SCRIPT = ROOT / "benchmarks" / "bench_nodes.py"
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
DEADLINE_S = 900  # a sweep of two short runs; a machine at load 30 takes minutes to start


@pytest.mark.parametrize("cameras, nodes, want", [
    (8, 2, [(0, 3), (4, 7)]),
    (32, 4, [(0, 7), (8, 15), (16, 23), (24, 31)]),
    (9, 4, [(0, 2), (3, 4), (5, 6), (7, 8)]),   # the first node takes the odd one
    (5, 4, [(0, 1), (2, 2), (3, 3), (4, 4)]),
    (4, 4, [(0, 0), (1, 1), (2, 2), (3, 3)]),
    (2, 1, [(0, 1)]),
])
def test_cameras_are_split_as_evenly_as_the_nodes_allow(cameras, nodes, want):
    got = bench_nodes.split_cameras(cameras, nodes)
    assert got == want
    served = [c for a, b in got for c in range(a, b + 1)]
    assert served == list(range(cameras))  # each camera on exactly one node, in order


@pytest.mark.parametrize("argv, says", [
    (["--cameras", "3", "--nodes", "4"], "3 cameras cannot go on 4 nodes"),
    (["--nodes", "5"], "--nodes 5"),
    (["--nodes", "0"], "--nodes 0"),
    (["--cameras", "40"], "--cameras 40"),
    (["--cameras", "1"], "--cameras 1"),
    (["--sweep", "--nodes", "2,4,6"], "--nodes 6"),
    (["--cameras", "8,x"], "'8,x'"),
    (["--cameras", "8", "--seconds", "0"], "--seconds 0"),
    (["--seconds", "20", "--steady", "18"], "--steady 18"),
    (["--steady", "-1"], "--steady -1"),
])
def test_a_bad_configuration_is_refused_in_one_line_before_anything_runs(argv, says, capsys):
    with pytest.raises(SystemExit) as exc:
        bench_nodes.main(argv)
    assert exc.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1 and says in err and "Traceback" not in err, err
    with pytest.raises(ValueError):
        bench_nodes.split_cameras(3, 4)


@pytest.mark.slow
def test_the_command_line_refuses_with_exit_2_and_one_line():
    r = subprocess.run([sys.executable, str(SCRIPT), "--cameras", "3", "--nodes", "4"],
                       cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        "bench_nodes.py: 3 cameras cannot go on 4 nodes: each node serves at least one"]


def _our_namespaces(pid: int) -> list[str]:
    """The namespaces the benchmark run `pid` made and has not deleted."""
    if shutil.which("ip") is None:
        return []
    r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
    return [line.split()[0] for line in r.stdout.splitlines()
            if line.startswith(f"{nodes_netns.PREFIX}{pid}")]


def _group_gone(pgid: int, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


@pytest.mark.slow
def test_a_2_node_4_camera_sweep_prints_its_rows_and_leaves_nothing_behind(tmp_path):
    """The local run, then 4 cameras on 2 nodes on loopback and in network namespaces: a
    row each; the nodes served the cameras the split gave them, the poses track the
    simulator's truth, and afterwards no process of the run and none of its namespaces
    is left. Where namespaces cannot be made, that row says why."""
    out = tmp_path / "sweep.json"
    p = subprocess.Popen([sys.executable, str(SCRIPT), "--cameras", "4", "--nodes", "2",
                          "--where", "both", "--seconds", "2", "--json", str(out)],
                         cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, start_new_session=True)
    stdout, stderr = p.communicate(timeout=DEADLINE_S)
    assert p.returncode == 0, stderr[-2000:]
    assert _group_gone(p.pid, 60), "a daemon or node of the run is still running"
    assert _our_namespaces(p.pid) == []
    rows = {(r["nodes"], r["where"]): r for r in json.loads(out.read_text())["runs"]}
    assert set(rows) == {(0, "local"), (2, "processes"), (2, "netns")}
    lines = stdout.splitlines()
    why = nodes_netns.why_not()
    for (nodes, where), r in rows.items():
        (line,) = [x for x in lines if nodes_sweep.WHERE[where] in x and not x.startswith("[")]
        if where == "netns" and why:
            assert "not run" in line and why in stdout
            continue
        assert "not run" not in line, stdout
        assert 0 <= r["steady"]["complete"] <= 1 and r["steady"]["sets"] > 0
        # tracking against the simulator's truth, as tests/test_nodes.py bounds it
        assert r["tracking"]["position_error_mm_rms"] < 2.0
        assert r["tracking"]["valid_fraction_min"] > 0.5
        if nodes:
            served = {n["name"]: n["cameras"] for n in r["steady"]["end"]["nodes"]}
            assert served == {"n0": ["cam0", "cam1"], "n1": ["cam2", "cam3"]}
            assert r["hop"]["hop_true_ms_median"] is not None


@pytest.mark.slow
def test_a_sweep_stopped_in_its_namespaces_run_removes_them_and_its_processes():
    """SIGTERM to the benchmark alone (its daemon and nodes are not signalled) while its
    nodes run in network namespaces: it stops every process it started and deletes every
    namespace it made. (The local run comes first and takes its 4 s window; the signal
    comes 3 s after the namespaces are made, before the daemon and nodes in them are even
    steady, let alone through the settling second and their own 4 s window: the run in
    the namespaces cannot end before the signal however fast the machine. A 10 s window
    checked nothing more and cost 6 s of the local run.)"""
    why = nodes_netns.why_not()
    if why:
        pytest.skip(why)
    p = subprocess.Popen([sys.executable, str(SCRIPT), "--cameras", "4", "--nodes", "2",
                          "--where", "netns", "--seconds", "4"], cwd=ROOT, env=ENV,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        end = time.monotonic() + DEADLINE_S
        while len(_our_namespaces(p.pid)) < 3 and time.monotonic() < end:
            assert p.poll() is None, p.stderr.read()[-2000:]
            time.sleep(0.5)
        assert len(_our_namespaces(p.pid)) == 3  # the daemon's and two nodes'
        time.sleep(3)  # the daemon and nodes starting inside them
        p.send_signal(signal.SIGTERM)
        p.wait(300)
        assert p.returncode == 130 and "interrupted" in p.stderr.read()
        assert _group_gone(p.pid, 60), "a daemon or node of the run is still running"
        assert _our_namespaces(p.pid) == []
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        for ns in _our_namespaces(p.pid):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_a_row_that_cannot_run_says_why_and_the_sweep_goes_on(monkeypatch, capsys):
    """Where namespaces cannot be made, their row says "not run" with the reason in a note
    (no namespace is attempted); a configuration that fails is reported the same way and
    the sweep goes on to the next."""
    ran = []

    def fails(tmp, cameras, nodes, where, publish, seconds):
        ran.append((cameras, nodes, where))
        raise nodes_sweep.RunFailed("the daemon ended early (exit code 1)")

    monkeypatch.setattr(nodes_netns, "why_not", lambda: "network namespaces need root")
    monkeypatch.setattr(nodes_sweep, "run_one", fails)
    nodes_sweep.sweep([4, 6], [2], "both", ("cameras",), 1.0, None)
    out = capsys.readouterr().out
    assert ran == [(4, 0, "local"), (4, 2, "processes"), (6, 0, "local"), (6, 2, "processes")]
    rows = [x for x in out.splitlines()
            if any(label in x for label in nodes_sweep.WHERE.values()) and x[:1] == " "]
    assert len(rows) == 6 and all("not run [" in x for x in rows), out
    assert "network namespaces: network namespaces need root" in out
    assert "4 cameras, 2 nodes, local processes: the daemon ended early (exit code 1)" in out
