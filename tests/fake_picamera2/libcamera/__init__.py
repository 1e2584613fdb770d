"""Fake ``libcamera`` Python bindings (apt ``python3-libcamera``): the parts picamera2 uses.

Missing when picamera2 comes from PyPI without the apt package: ``import libcamera`` in
picamera2/picamera2.py is its first failing line (ModuleNotFoundError, name "libcamera").
"""

import fakecam_rig

if not fakecam_rig.rig.libcamera_installed:
    raise ModuleNotFoundError("No module named 'libcamera'", name="libcamera")


class ColorSpace:
    """libcamera.ColorSpace presets (picamera2.py create_*_configuration use these)."""

    def __init__(self, name: str, full_range: bool) -> None:
        self.name, self.full_range = name, full_range

    def __repr__(self) -> str:
        return f"<libcamera.ColorSpace '{self.name}'>"

    @staticmethod
    def Sycc() -> "ColorSpace":
        return ColorSpace("sYCC", True)

    @staticmethod
    def Rec709() -> "ColorSpace":
        return ColorSpace("Rec709", False)

    @staticmethod
    def Smpte170m() -> "ColorSpace":
        return ColorSpace("SMPTE170M", False)


class Transform:
    def __init__(self, hflip: int = 0, vflip: int = 0) -> None:
        self.hflip, self.vflip = hflip, vflip


class _Camera:
    def __init__(self, info: dict) -> None:
        self.id = info["Id"]
        self.properties = {k: v for k, v in info.items() if k != "Id"}


class CameraManager:
    _instance: "CameraManager | None" = None

    @classmethod
    def singleton(cls) -> "CameraManager":
        if cls._instance is None:
            cls._instance = cls()
        return cls._instance

    @property
    def cameras(self) -> list[_Camera]:
        return [_Camera(c) for c in fakecam_rig.rig.cameras]
