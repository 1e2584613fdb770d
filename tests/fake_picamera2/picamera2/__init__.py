"""Fake ``picamera2`` package: the import chain and the classes KMEA uses.

As the real package's __init__ (raspberrypi/picamera2 picamera2/__init__.py): importing it
imports picamera2.picamera2, which imports ``libcamera`` first and, through
picamera2.encoders.jpeg_encoder, the apt ``simplejpeg`` (issue 1088's traceback).
"""

import libcamera  # noqa: F401 - picamera2/picamera2.py: `import libcamera` (first native import)
import simplejpeg  # noqa: F401 - picamera2/encoders/jpeg_encoder.py: `import simplejpeg`

from .job import Job
from .picamera2 import Picamera2
from .request import CompletedRequest, MappedArray

__all__ = ["CompletedRequest", "Job", "MappedArray", "Picamera2"]
