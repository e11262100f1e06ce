"""Network namespaces for bench_nodes.py: the daemon in one, each node in its own, veth-joined.

On loopback the nodes' blobs never leave the kernel's loopback path; in namespaces they
cross a veth pair each, as they would cross a NIC (the same machine's cores still serve
every process: what differs is the network stack's path, not the hardware). Node k's pair
is 10.214.k.1 (the daemon's end) / 10.214.k.2 (the node's), a /30 each: these addresses
exist only inside the namespaces made here, never on the machine's own network, and every
namespace (with its veth ends) is deleted on exit, on error and on Ctrl-C. Namespaces of a
run that was killed outright (SIGKILL leaves no time to clean up) carry its process id in
their names and are removed by the next run once that process is gone.

Needs root and `ip` (iproute2); `why_not()` says in one line why it cannot run here.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

PREFIX = "mcdb"  # namespace names: mcdb<pid>d (daemon), mcdb<pid>n<k> (node k)
PORT = 7447  # inside the daemon's own namespace: nothing else listens there


class NetnsError(RuntimeError):
    """The namespaces could not be made: the message says why (one line)."""


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True)


def why_not() -> str | None:
    """None if this machine can make network namespaces and veth pairs, else why not."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "`ip` (iproute2) is not installed"
    probe = f"{PREFIX}{os.getpid()}p"
    r = _ip("netns", "add", probe)
    if r.returncode != 0:
        return f"cannot make a network namespace: {r.stderr.strip()}"
    try:
        va, vb = f"mcbp{os.getpid() % 100000}a", f"mcbp{os.getpid() % 100000}b"
        r = _ip("-n", probe, "link", "add", va, "type", "veth", "peer", "name", vb)
        if r.returncode != 0:
            return f"cannot make a veth pair: {r.stderr.strip()}"
    finally:
        _ip("netns", "del", probe)  # its veth pair goes with it
    return None


def remove_stale() -> list[str]:
    """Delete the namespaces of bench_nodes runs whose process is gone (killed outright);
    the names removed."""
    r = _ip("netns", "list")
    gone = []
    for line in r.stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        m = re.fullmatch(rf"{PREFIX}(\d+)[dnp]\d*", name)
        if m and not Path(f"/proc/{m.group(1)}").exists():
            _ip("netns", "del", name)
            gone.append(name)
    return gone


class Namespaces:
    """The daemon's namespace and one per node, each node's joined to the daemon's by a veth
    pair; a context manager that deletes them all on the way out, however it is left."""

    def __init__(self, nodes: int) -> None:
        pid = os.getpid()
        self.daemon = f"{PREFIX}{pid}d"
        self.nodes = [f"{PREFIX}{pid}n{k}" for k in range(nodes)]
        self._veth = [(f"mcb{pid % 100000}d{k}", f"mcb{pid % 100000}n{k}")
                      for k in range(nodes)]
        self._made: list[str] = []

    def daemon_address(self, k: int) -> str:
        return f"10.214.{k}.1"

    def listen(self) -> list[str]:
        """The daemon's Zenoh endpoints: its end of every node's pair."""
        return [f"tcp/{self.daemon_address(k)}:{PORT}" for k in range(len(self.nodes))]

    def connect(self, k: int) -> str:
        return f"tcp/{self.daemon_address(k)}:{PORT}"

    def exec(self, ns: str) -> list[str]:
        """The command prefix that runs a program inside namespace `ns` (`ip netns exec`
        execs the program in place: its process id is the program's)."""
        return ["ip", "netns", "exec", ns]

    def _run(self, *args: str) -> None:
        r = _ip(*args)
        if r.returncode != 0:
            raise NetnsError(f"ip {' '.join(args)}: {r.stderr.strip()}")

    def __enter__(self) -> Namespaces:
        remove_stale()
        try:
            for ns in (self.daemon, *self.nodes):
                self._run("netns", "add", ns)
                self._made.append(ns)
                self._run("-n", ns, "link", "set", "lo", "up")
            for k, (ns, (vd, vn)) in enumerate(zip(self.nodes, self._veth, strict=True)):
                self._run("-n", self.daemon, "link", "add", vd, "type", "veth", "peer", "name",
                          vn, "netns", ns)
                self._run("-n", self.daemon, "addr", "add", f"10.214.{k}.1/30", "dev", vd)
                self._run("-n", ns, "addr", "add", f"10.214.{k}.2/30", "dev", vn)
                self._run("-n", self.daemon, "link", "set", vd, "up")
                self._run("-n", ns, "link", "set", vn, "up")
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Delete every namespace made (a veth pair goes with the namespace of either end).
        The processes inside should be stopped first: a namespace with a process still in
        it loses its name but lives on until that process ends."""
        for ns in reversed(self._made):
            _ip("netns", "del", ns)
        self._made.clear()

    def __exit__(self, *exc) -> None:
        self.close()
