"""The renderer's pixel sampling: sub-pixel ray patterns and the edge masks that decide
which pixels take many rays."""

from __future__ import annotations

import numpy as np

__all__ = ["DYNAMIC_SAMPLES", "STATIC_BIT", "STATIC_SAMPLES", "edges", "fib_pattern",
           "fib_pattern32", "or_dilate"]


def fib_pattern(n: int, g: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel offsets (n,) x2 of a rank-1 (Fibonacci) lattice over [-0.5, 0.5)^2."""
    k = np.arange(n)
    return ((k + 0.5) / n - 0.5), (((k * g) % n) + 0.5) / n - 0.5


def fib_pattern32(n: int, g: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fib_pattern` in float32."""
    du, dv = fib_pattern(n, g)
    return du.astype(np.float32), dv.astype(np.float32)


STATIC_SAMPLES = fib_pattern32(89, 55)
DYNAMIC_SAMPLES = fib_pattern32(34, 21)


def edges(a: np.ndarray) -> np.ndarray:
    """Pixels whose value differs from one of their 8 neighbours."""
    m = np.zeros(a.shape, dtype=bool)
    d = a[:, 1:] != a[:, :-1]
    m[:, 1:] |= d
    m[:, :-1] |= d
    d = a[1:, :] != a[:-1, :]
    m[1:, :] |= d
    m[:-1, :] |= d
    d = a[1:, 1:] != a[:-1, :-1]
    m[1:, 1:] |= d
    m[:-1, :-1] |= d
    d = a[1:, :-1] != a[:-1, 1:]
    m[1:, :-1] |= d
    m[:-1, 1:] |= d
    return m


STATIC_BIT = np.int64(1) << np.int64(62)


def or_dilate(a: np.ndarray) -> np.ndarray:
    """Bitwise OR of each value with its 8 neighbours."""
    m = a.copy()
    m[:, 1:] |= a[:, :-1]
    m[:, :-1] |= a[:, 1:]
    h = m.copy()
    m[1:, :] |= h[:-1, :]
    m[:-1, :] |= h[1:, :]
    return m
