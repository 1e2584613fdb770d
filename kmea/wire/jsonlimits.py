"""JSON from the network, with limits: size, nesting depth, no NaN/Infinity (stdlib only).

``json.loads`` recurses once per nesting level: ``b"[" * 1000 + b"]" * 1000`` raised
``RecursionError`` inside the control thread. The depth is measured before parsing, on the
bracket characters outside strings, in linear time. Standard library only.
"""

from __future__ import annotations

import json
import re
from itertools import accumulate
from typing import Any

__all__ = ["MAX_DEPTH", "JsonLimitError", "json_depth", "safe_loads"]

MAX_DEPTH = 32

# A JSON string literal (escapes included); what is inside never counts as nesting.
_STRING_RE = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
_STEP = bytes.maketrans(b"[{]}", b"\x01\x01\x02\x02")
_OTHER_RE = re.compile(rb"[^\[\]{}]+")


class JsonLimitError(ValueError):
    """JSON refused before or while parsing; the message says why, in one line."""


def json_depth(data: bytes, limit: int = MAX_DEPTH) -> int:
    """Nesting depth of ``[``/``{`` outside string literals (0 for a scalar).

    Linear time (about 0.25 us a bracket); a document with at most ``limit`` opening
    brackets in all is answered without the walk.
    """
    if data.count(b"[") + data.count(b"{") <= limit:
        return data.count(b"[") + data.count(b"{")  # an upper bound within the limit
    brackets = _OTHER_RE.sub(b"", _STRING_RE.sub(b"", data))
    if not brackets:
        return 0
    return max(accumulate(1 if s == 1 else -1 for s in brackets.translate(_STEP)))


def _no_constant(name: str) -> Any:
    raise JsonLimitError(f"{name} is not JSON")


def safe_loads(data: bytes, max_bytes: int, max_depth: int = MAX_DEPTH) -> Any:
    """Parse UTF-8 JSON ``data`` of at most ``max_bytes`` and ``max_depth`` levels.

    Raises :class:`JsonLimitError` (a ``ValueError``) for anything else: too large, too deep,
    not UTF-8, not JSON, NaN or Infinity, numbers with thousands of digits.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise JsonLimitError(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > max_bytes:
        raise JsonLimitError(f"message too large ({len(data)} bytes, at most {max_bytes})")
    depth = json_depth(data, max_depth)
    if depth > max_depth:
        raise JsonLimitError(f"JSON nested too deeply ({depth} levels, at most {max_depth})")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise JsonLimitError(f"body is not UTF-8 JSON: {e}") from None
    try:
        return json.loads(text, parse_constant=_no_constant)
    except JsonLimitError:
        raise
    except RecursionError:  # unreachable after the depth check; never let it escape
        raise JsonLimitError("JSON nested too deeply") from None
    except ValueError as e:  # JSONDecodeError, int() of a 5000-digit number
        raise JsonLimitError(f"body is not UTF-8 JSON: {str(e)[:120]}") from None
