"""The bytes of a recording file: JSON lines, plain or zstd-compressed, whole lines only.

A name ending in ``.zst`` (``run.jsonl.zst``) is written as one zstd stream in which every
line is flushed as a complete block (``COMPRESSOBJ_FLUSH_BLOCK``): whatever a kill or a
full disk leaves on disk decompresses to a prefix of the lines, and every line written
before the last flush is whole. The same file is ``zstdcat``-readable. Any other name is
plain JSON lines, as the first recordings were (``kmea bench recording-size`` measures
both: zstd keeps about 1/3 of a frame whose numbers all change and 1/40 of a fast-path
frame, at a fraction of a millisecond a frame).

Readers look at the first bytes, not the name: a compressed recording renamed ``.jsonl``
still reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import zstandard

from kmea.recordings import wholewrite

__all__ = ["ZSTD_MAGIC", "LineWriter", "RecordingBytesError", "is_compressed_name",
           "read_lines"]

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
# zstd level 3 (its default): levels 9+ save 5-8 % more at 4-6 times the CPU a frame.
ZSTD_LEVEL = 3
_READ_CHUNK = 1 << 16
_IN_PIECE = 1 << 11


class RecordingBytesError(ValueError):
    """Bytes that are not a readable recording (corrupt compressed data)."""


def is_compressed_name(path: str | Path) -> bool:
    return str(path).endswith(".zst")


class LineWriter:
    """Appends whole lines to a new file (compressed when the name ends in ``.zst``).

    ``bytes`` counts what is on disk. A failed write (``OSError``: a full disk) is cut back
    to the last whole line (:func:`kmea.recordings.wholewrite.write_whole`) and raised; the
    writer is
    then broken: close() closes the file without writing more (the stream's end is not
    needed to read it)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.compressed = is_compressed_name(path)
        self._z = (zstandard.ZstdCompressor(level=ZSTD_LEVEL).compressobj()
                   if self.compressed else None)
        self._f = wholewrite.open_output(path)
        self.bytes = 0  # the byte after the last whole line
        self._broken = False

    def write(self, text: bytes) -> None:
        if self._broken:
            raise OSError(f"{self.path}: an earlier write failed")
        data = text if self._z is None else (
            self._z.compress(text) + self._z.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK))
        try:
            wholewrite.write_whole(self._f, data, self.bytes)
        except OSError:
            self._broken = True  # the compressor holds a line the file does not
            raise
        self.bytes += len(data)

    def close(self) -> None:
        if self._f.closed:
            return
        try:
            if self._z is not None and not self._broken:
                end = self._z.flush(zstandard.COMPRESSOBJ_FLUSH_FINISH)
                wholewrite.write_whole(self._f, end, self.bytes)
                self.bytes += len(end)
        finally:
            self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed


def read_lines(f: Any) -> Iterator[bytes]:
    """The lines of the binary file ``f`` (plain or zstd, told by its first bytes), each
    with its newline; a last line without one is a cut line (a kill), yielded as it is so
    the caller can say so (``b""`` for a compressed stream cut between two lines).
    ``RecordingBytesError`` for corrupt compressed data, after the lines before it."""
    first = f.read(_READ_CHUNK)
    chunks = _chunks(f, first)
    if not first.startswith(ZSTD_MAGIC):
        yield from _split(chunks)
        return
    ended = [True]
    last = b"\n"
    for last in _split(_unzstd(chunks, ended)):
        yield last
    if not ended[0] and last.endswith(b"\n"):
        yield b""  # cut between two blocks: whole lines, but the stream has no end mark


def _chunks(f: Any, first: bytes) -> Iterator[bytes]:
    data = first
    while data:
        yield data
        data = f.read(_READ_CHUNK)


def _unzstd(chunks: Iterator[bytes], ended: list[bool]) -> Iterator[bytes]:
    """Decompressed pieces; a stream cut short ends quietly after its last whole block
    (``ended[0]`` is then False)."""
    d = zstandard.ZstdDecompressor().decompressobj()
    for chunk in chunks:
        # Small pieces in: a corrupt block loses only the lines of its piece (one call
        # that raises returns nothing of what it decoded before the bad block).
        for i in range(0, len(chunk), _IN_PIECE):
            data = chunk[i:i + _IN_PIECE]
            while data:
                ended[0] = False
                try:
                    yield d.decompress(data)
                except zstandard.ZstdError as e:
                    raise RecordingBytesError(f"corrupt compressed data: {e}") from None
                data = b""
                if d.eof:  # a stream ended; another may follow (files joined with cat)
                    data = d.unused_data
                    d = zstandard.ZstdDecompressor().decompressobj()
                    ended[0] = True


def _split(pieces: Iterator[bytes]) -> Iterator[bytes]:
    pending: list[bytes] = []
    for piece in pieces:
        start = 0
        while (nl := piece.find(b"\n", start)) >= 0:
            pending.append(piece[start:nl + 1])
            yield b"".join(pending)
            pending = []
            start = nl + 1
        if start < len(piece):
            pending.append(piece[start:])
    if pending:
        yield b"".join(pending)
