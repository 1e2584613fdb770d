"""Telemetry and control over ZeroMQ, CURVE keys, the message bodies."""
