"""mocapd's log lines: plain on a terminal, with the syslog priority prefix on the journal.

Why a prefix and not a library: systemd reads a `<N>` at the start of each line a service
writes to stdout or stderr as that line's priority (SyslogLevelPrefix=, on by default), so
`journalctl -p warning -u mocapd` finds the warnings and errors without journald bindings.
Systemd says a program may rely on that only when JOURNAL_STREAM names the very stream it
writes to (device and inode), not merely when the variable is set: a child started from a
service with its stderr sent to a file inherits the variable.
"""

from __future__ import annotations

import logging
import os
import sys

# logging level -> syslog priority (RFC 5424): 7 debug, 6 info, 4 warning, 3 error, 2 crit
PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
            logging.CRITICAL: 2}


def priority(levelno: int) -> int:
    """The syslog priority of a logging level (levels between the named ones round up)."""
    for level in sorted(PRIORITY, reverse=True):
        if levelno >= level:
            return PRIORITY[level]
    return 7


def writes_to_journal(stream) -> bool:
    """Whether `stream` is the journal's stream systemd connected this service to."""
    value = os.environ.get("JOURNAL_STREAM", "")
    dev, _, ino = value.partition(":")
    if not (dev.isdigit() and ino.isdigit()):
        return False
    try:
        st = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):  # a stream without a file (test capture)
        return False
    return (st.st_dev, st.st_ino) == (int(dev), int(ino))


class JournalFormatter(logging.Formatter):
    """`<priority>message`, one prefix per line (a multi-line message keeps its priority)."""

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def setup_logging(verbose: bool = False, stream=None) -> None:
    """The "mocapd" logger to stderr: `mocapd: message` for a person, `<N>message` for
    the journal (which names the unit itself). Called again, it follows the current
    stderr (test runners replace it) and re-decides the format."""
    stream = stream or sys.stderr
    root = logging.getLogger("mocapd")
    ours = [h for h in root.handlers if getattr(h, "_mocapd", False)]
    handler = ours[0] if ours else logging.StreamHandler(stream)
    handler.stream = stream
    handler.setFormatter(JournalFormatter("%(message)s") if writes_to_journal(stream)
                         else logging.Formatter("mocapd: %(message)s"))
    if not ours:
        handler._mocapd = True
        root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    root.propagate = False
