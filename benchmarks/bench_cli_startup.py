"""What `--help` costs: start-up time of calibkit's and mocapd's help screens (issue 31).

Each case runs --repeats times in a child process (wall time, and CPU time from os.wait4,
which the machine's load disturbs less), with bytecode cached in __pycache__ and with none:
PYTHONDONTWRITEBYTECODE set and PYTHONPYCACHEPREFIX an empty folder, so every start compiles
everything it imports, as on the machines of issue 31. The baseline in the same run is
`python -c pass`. --before DIR runs the same cases again on another source tree (calibkit,
daemon and projector put first on PYTHONPATH), e.g. the code before issue 31:

    git archive 7c34685 calibkit daemon projector | tar -x -C /tmp/before

--importtime prints the slowest imports of `calibkit --help` (python -X importtime,
cumulative microseconds).

    python benchmarks/bench_cli_startup.py [--repeats 7] [--before DIR] [--importtime]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUN = "import sys; sys.argv = {argv!r}; from {app} import main; main()"


def _cases() -> list[tuple[str, list[str]]]:
    def cli(app: str, *argv: str) -> list[str]:
        prog = "calibkit" if app == "calibkit.cli" else "mocapd"
        return [sys.executable, "-c", RUN.format(argv=[prog, *argv], app=app)]

    return [
        ("python -c pass (baseline)", [sys.executable, "-c", "pass"]),
        ("calibkit --help", cli("calibkit.cli", "--help")),
        ("mocapd --help", cli("daemon.cli", "--help")),
        ("calibkit wand --help", cli("calibkit.cli", "wand", "--help")),
        ("calibkit detect --help", cli("calibkit.cli", "detect", "--help")),
        ("calibkit sim rig --help", cli("calibkit.cli", "sim", "rig", "--help")),
        ("mocapd start --help", cli("daemon.cli", "start", "--help")),
        ("mocapd label --help", cli("daemon.cli", "label", "--help")),
    ]


def _child(argv: list[str], env: dict[str, str], cwd: str) -> tuple[float, float]:
    """(wall s, CPU s) of one child process, run in `cwd` (not the source tree, which
    `python -c` would put first on sys.path); a failure stops the benchmark."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            cwd=cwd)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    err = proc.stderr.read().decode(errors="replace")
    proc.stderr.close()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{argv} exited {proc.returncode}: {err.strip()[-500:]}")
    return wall, usage.ru_utime + usage.ru_stime


def _importtime(top: int) -> None:
    res = subprocess.run([sys.executable, "-X", "importtime", "-c",
                          RUN.format(argv=["calibkit", "--help"], app="calibkit.cli")],
                         capture_output=True, text=True, check=True, cwd=tempfile.gettempdir())
    rows = []
    for line in res.stderr.splitlines():
        if line.startswith("import time:") and "|" in line and "cumulative" not in line:
            _, cumulative, name = line[len("import time:"):].split("|")
            rows.append((int(cumulative), name.rstrip()))
    print(f"\n`calibkit --help` imports {len(rows)} modules; slowest (cumulative us):")
    for cumulative, name in sorted(rows, reverse=True)[:top]:
        print(f"{cumulative:>10}  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--importtime", action="store_true")
    parser.add_argument("--before", type=Path, help="another source tree to time too")
    args = parser.parse_args()
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} "
          f"{os.getloadavg()[2]:.2f} (1, 5, 15 min) on {os.cpu_count()} cores; "
          f"median of {args.repeats} runs")
    base_env = {k: v for k, v in os.environ.items()
                if k not in ("PYTHONDONTWRITEBYTECODE", "PYTHONPYCACHEPREFIX")}
    trees = {"": base_env}
    if args.before is not None:
        if not (args.before / "calibkit" / "cli.py").is_file():
            raise SystemExit(f"--before {args.before}: no calibkit/cli.py there")
        path = os.pathsep.join(p for p in (str(args.before.resolve()),
                                           base_env.get("PYTHONPATH")) if p)
        trees["before: "] = dict(base_env, PYTHONPATH=path)
    header = ["case"] + [f"{e} {k}" for e in ("cached", "no bytecode")
                         for k in ("wall s", "CPU s")]
    width = 34
    print(f"{header[0]:<{width}}  " + "  ".join(f"{h:>18}" for h in header[1:]), flush=True)
    with tempfile.TemporaryDirectory() as empty:
        for label, env in trees.items():
            envs = [env, dict(env, PYTHONDONTWRITEBYTECODE="1", PYTHONPYCACHEPREFIX=empty)]
            for _, argv in _cases():  # warm the bytecode and page caches first
                _child(argv, env, empty)
            for name, argv in _cases():
                if label and name.startswith("python"):
                    continue
                row = []
                for e in envs:
                    runs = [_child(argv, e, empty) for _ in range(args.repeats)]
                    row += [statistics.median(r[0] for r in runs),
                            statistics.median(r[1] for r in runs)]
                print(f"{label + name:<{width}}  " + "  ".join(f"{v:>18.3f}" for v in row),
                      flush=True)
    if args.importtime:
        _importtime(12)


if __name__ == "__main__":
    main()
