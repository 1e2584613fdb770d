"""Recordings (format, bytes on disk) and whole-record file writes."""
