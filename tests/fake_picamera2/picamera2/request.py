"""picamera2/request.py: CompletedRequest and MappedArray, as far as KMEA uses them."""

from __future__ import annotations

from typing import Any

import numpy as np


class CompletedRequest:
    """One completed libcamera request: a frame buffer per stream and its metadata.

    Reference counted (request.py ``acquire``/``release``): the caller of capture_request holds
    one reference; at zero the buffer goes back to the camera (and is unusable: ``request``
    becomes None, so mapping it again fails the ``assert request.request is not None`` in
    ``_MappedBuffer``). Releasing below zero raises RuntimeError, as the real one.
    """

    def __init__(self, picam2: Any, buffer: np.ndarray, metadata: dict) -> None:
        self.picam2 = picam2
        self.request: np.ndarray | None = buffer  # stands for the libcamera Request
        self.ref_count = 1
        self.config = dict(picam2.camera_config)
        self._metadata = dict(metadata)

    def acquire(self) -> None:
        if self.ref_count == 0:
            raise RuntimeError("CompletedRequest: acquiring lock with ref_count 0")
        self.ref_count += 1

    def release(self) -> None:
        self.ref_count -= 1
        if self.ref_count < 0:
            raise RuntimeError("CompletedRequest: lock now has negative ref_count")
        if self.ref_count == 0:
            self.picam2._returned(self)
            self.request = None

    def get_metadata(self) -> dict:
        assert self.request is not None
        return dict(self._metadata)

    def make_buffer(self, name: str) -> np.ndarray:
        """1D copy of the stream's buffer (request.py: ``np.array(b, dtype=np.uint8)``)."""
        if name != "main":
            raise RuntimeError(f"Stream {name!r} is not defined")
        assert self.request is not None
        return np.array(self.request.reshape(-1), dtype=np.uint8)

    def make_array(self, name: str) -> np.ndarray:
        """A copy shaped as Helpers.make_array: YUV420 -> (H * 3/2, stride), padding kept."""
        return _shape(self.make_buffer(name), self.config[name])


def _shape(flat: np.ndarray, config: dict) -> np.ndarray:
    fmt = config["format"]
    h = config["size"][1]
    stride = config["stride"]
    if fmt in ("YUV420", "YVU420"):
        # request.py: "Returning YUV420 as an image of 50% greater height ... We leave any
        # packing in there" -> (h * 3 // 2, stride), the row padding is the caller's to drop.
        return flat.reshape((h * 3 // 2, stride))
    raise RuntimeError("Format " + fmt + " not supported")


class MappedArray:
    """request.py MappedArray(request, stream, reshape=True, write=True): a context manager
    giving the stream's buffer itself (no copy) as ``.array``, shaped as make_array; ``write``
    (newer picamera2 only) chooses the DMA-buf sync direction there (here: a read-only
    view, so a write through it would show). After ``__exit__`` the array is deleted."""

    def __init__(self, request: CompletedRequest, stream: str, reshape: bool = True,
                 write: bool = True) -> None:
        assert request.request is not None  # _MappedBuffer: the request must not be released
        self.__request = request
        self.__stream = stream
        self.__reshape = reshape
        self.__write = write
        self.__array: np.ndarray | None = None

    def __enter__(self) -> MappedArray:
        buf = self.__request.request
        assert buf is not None
        array = buf.reshape(-1)[:]  # a view of the frame buffer: no copy
        if not self.__write:
            array = array.view()
            array.flags.writeable = False
        if self.__reshape:
            array = _shape(array, self.__request.config[self.__stream])
        self.__array = array
        return self

    def __exit__(self, *exc: object) -> None:
        if self.__array is not None:
            del self.__array

    @property
    def array(self) -> np.ndarray | None:
        return self.__array
