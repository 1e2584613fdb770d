"""TOML read with bounds (stdlib only: the terminal UI imports it).

:func:`loads` is how every TOML file of the project is read (configuration, map, camera):
nesting beyond :data:`MAX_DEPTH` is refused before ``tomllib`` sees it, since tomllib
recurses once per level and a few hundred levels overflow the interpreter's stack (the
``RecursionError`` could then surface through an unrelated finaliser, printed as "Exception
ignored", at the garbage collector's whim). :func:`parse_toml_value` reads one typed-in value
(``kmead --set KEY=VALUE``, the UI's settings form), so both read ``1.0``, ``true``,
``"DICT_6X6_250"``, ``[40, 41]`` the same way.
"""

from __future__ import annotations

import sys
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["MAX_DEPTH", "TOMLDecodeError", "TooDeep", "loads", "parse_toml_value"]

MAX_DEPTH = 64  # arrays and inline tables in one another; no kmea file needs more than 4
TOMLDecodeError = tomllib.TOMLDecodeError


class TooDeep(ValueError):
    """TOML nested deeper than :data:`MAX_DEPTH`."""


def _depth(text: str) -> int:
    """The deepest nesting of ``[``/``{`` outside strings and comments (a table header counts
    its own brackets: at most 2)."""
    depth = deepest = 0
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c == "#":
            j = text.find("\n", i)
            i = n if j < 0 else j
            continue
        if c in "\"'":
            triple = text.startswith(c * 3, i)
            quote = c * 3 if triple else c
            i += len(quote)
            while i < n and not text.startswith(quote, i):
                if c == '"' and text[i] == "\\":
                    i += 1
                elif not triple and text[i] == "\n":
                    break  # an unclosed string: tomllib will say where
                i += 1
            i += len(quote)
            continue
        if c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth = max(depth - 1, 0)
        i += 1
    return deepest


def loads(text: str) -> dict[str, Any]:
    """``tomllib.loads`` with the nesting bounded: :class:`TooDeep` beyond :data:`MAX_DEPTH`
    levels, ``TOMLDecodeError`` as tomllib raises it."""
    d = _depth(text)
    if d > MAX_DEPTH:
        raise TooDeep(f"nested too deeply ({d} levels, at most {MAX_DEPTH})")
    return tomllib.loads(text)


def parse_toml_value(text: str) -> Any:
    """``text`` (stripped) as a TOML value; a bare word that is not TOML is that string.

    Shells strip quotes (``--set detector.dictionary="DICT_6X6_250"`` arrives unquoted), so
    a value that is not valid TOML is taken as a string; validation then decides.
    """
    text = text.strip()
    try:
        return loads(f"v = {text}")["v"]
    except (tomllib.TOMLDecodeError, TooDeep):
        return text
