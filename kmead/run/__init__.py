"""The run loop: start-up, capture, the daemon, live settings on trial, what it
reports (summary, status line, systemd, log ring, camera thumbnails)."""
