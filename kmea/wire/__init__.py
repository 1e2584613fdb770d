"""The wire protocol and its standard-library helpers: the only part of kmea the
terminal UI imports (tests/test_layers.py)."""
