"""Benchmarks behind ``kmea bench`` (they print figures)."""
