"""JSON-safe copies of Python and numpy data (stdlib only: the wire protocol imports it).

The one place that decides how data becomes JSON: telemetry bodies, recordings, the
simulator's truth files and the daemon's ground-truth records all go through
:func:`to_jsonable`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, cast


def to_jsonable(obj: Any) -> Any:
    """A copy of ``obj`` that ``json.dumps(..., allow_nan=False)`` accepts.

    NaN and +-inf become ``None`` (JSON has neither); numpy arrays become nested lists and
    numpy scalars Python numbers (anything with ``tolist``); dataclass instances become dicts
    of their fields; dict keys become ``str``; tuples, lists and sets become lists (sets
    sorted when their items allow it); any other object becomes ``str(obj)``.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (set, frozenset)):
        try:
            items = sorted(obj)
        except TypeError:
            items = list(obj)
        return [to_jsonable(v) for v in items]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if hasattr(obj, "tolist"):  # numpy arrays and scalars, without importing numpy
        # (cast: the is_dataclass test above left obj narrowed to type[DataclassInstance])
        return to_jsonable(cast(Any, obj).tolist())
    return str(obj)
