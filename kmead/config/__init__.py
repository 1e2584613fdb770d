"""Configuration: every key declared once, the layers, the start-up plan and
``--check``."""
