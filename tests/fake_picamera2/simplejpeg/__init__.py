"""Fake apt ``simplejpeg``: a Cython extension built against one numpy major version.

picamera2 imports it at import time (picamera2/encoders/jpeg_encoder.py: ``import
simplejpeg``, traceback in raspberrypi/picamera2 issue 1088). Under the other numpy major,
Cython's type-size check fails on import with this ValueError (issue 1211: "numpy.dtype size
changed, may indicate binary incompatibility. Expected 96 from C header, got 88 from
PyObject" = built for numpy 1.x, running numpy 2.x, as on Bookworm with a venv numpy 2).
"""

import fakecam_rig

_built = fakecam_rig.rig.simplejpeg_numpy_major
_running = fakecam_rig.numpy_major()
if _built is not None and _built != _running:
    _sizes = {1: 96, 2: 88}  # sizeof(PyArray_Descr) in numpy 1.x / 2.x
    raise ValueError(f"numpy.dtype size changed, may indicate binary incompatibility. Expected "
                     f"{_sizes.get(_built, 96)} from C header, got {_sizes.get(_running, 88)} "
                     f"from PyObject")


def encode_jpeg(*args: object, **kwargs: object) -> bytes:  # pragma: no cover - unused
    raise NotImplementedError("the fake simplejpeg encodes nothing")
