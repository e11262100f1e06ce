"""Real-time scheduling for the live daemon: its threads ahead of ordinary work.

Why: on a machine doing anything else, the latency tail is not the daemon's work but the
kernel's scheduler. Measured with the per-stage figures (`latency_stages` in the figures),
the slowest 1 % of frames wait for a core, between a camera's sample arriving and the frame
loop starting on it, not in tracking; `nice -10` does not help, since the fair scheduler
still shares the core. Under SCHED_RR every thread of the daemon runs as soon as it is
woken, ahead of all normal processes (the kernel still keeps 5 % of each second for them,
so a runaway thread cannot lock the machine up).

Threads inherit the policy of the thread that starts them, so this runs on the main thread
before the capture threads, publishers and frame loop start. The web view's process starts
before it and stays at normal priority: only tracking runs ahead. (SCHED_RESET_ON_FORK is
not used: the kernel applies it to new threads too, which would leave them behind.)
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger("mocapd.realtime")

HOW_TO_ALLOW = ("allow it with LimitRTPRIO={p} in the systemd unit (mocapd install-unit "
                "writes it), `setcap cap_sys_nice+ep` on the Python binary, or an rtprio line "
                "in /etc/security/limits.conf; or leave it off (no --realtime, "
                "[pipeline] realtime_priority = 0)")


def raise_priority(priority: int) -> str:
    """Put the calling thread (and the threads it starts afterwards) under SCHED_RR at
    `priority` (1-99; 0: leave the scheduling alone). Returns what the daemon runs at, for
    `mocapd status`; when the system refuses, logs one warning saying how to allow it and
    goes on at normal priority."""
    if priority <= 0:
        return "normal (real-time scheduling not asked for: --realtime)"
    if not hasattr(os, "sched_setscheduler"):
        return "normal (this system has no real-time scheduling)"
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
    except PermissionError:
        log.warning("running at normal priority: the system refused real-time scheduling "
                    "(SCHED_RR %d), so other work on this machine can delay poses by "
                    "milliseconds; %s", priority, HOW_TO_ALLOW.format(p=priority))
        return f"normal (SCHED_RR {priority} refused)"
    except OSError as exc:  # e.g. a priority above what the kernel allows
        log.warning("running at normal priority: SCHED_RR %d failed (%s)", priority, exc)
        return f"normal (SCHED_RR {priority} failed: {exc.strerror})"
    # said once tracking starts (daemon.service.daemon), after the configuration has checked out
    log.debug("real-time priority: SCHED_RR %d", priority)
    return f"SCHED_RR {priority}"


def restore_normal() -> None:
    """Back to normal scheduling for the calling thread (a daemon run in-process, as the
    tests do, must not leave its caller real-time)."""
    if hasattr(os, "sched_setscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def current_policy() -> str:
    """The calling thread's scheduling policy by name (for tests and status)."""
    policy = os.sched_getscheduler(0)
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_RR: "SCHED_RR",
             os.SCHED_FIFO: "SCHED_FIFO"}
    return names.get(policy, str(policy))
