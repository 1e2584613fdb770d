"""One typed-in configuration value, read as TOML (stdlib only: the terminal UI imports it).

Used by ``kmead --set KEY=VALUE`` (:func:`kmead.config.layers.parse_set`) and the UI's settings
form, so both read ``1.0``, ``true``, ``"DICT_6X6_250"``, ``[40, 41]`` the same way.
"""

from __future__ import annotations

import sys
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["parse_toml_value"]


def parse_toml_value(text: str) -> Any:
    """``text`` (stripped) as a TOML value; a bare word that is not TOML is that string.

    Shells strip quotes (``--set detector.dictionary="DICT_6X6_250"`` arrives unquoted), so
    a value that is not valid TOML is taken as a string; validation then decides.
    """
    text = text.strip()
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):  # RecursionError: nested 600+ deep
        return text
