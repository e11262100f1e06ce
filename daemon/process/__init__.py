"""The plumbing of a long-running mocapd process (the daemon, a capture node): real-time
scheduling, the frozen heap, systemd's notify, log lines, worker threads."""
