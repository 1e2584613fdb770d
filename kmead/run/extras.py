"""A camera's kmead's optional outputs: robot poses on Zenoh with this kmead as a camera of
its site (``[zenoh]``, docs/ros2.md, docs/fusion.md) and the Foxglove viewer
(``[foxglove]``). :class:`kmead.run.daemon.Daemon` is built on this part of it; each output
registers its close on the service's teardown as it opens (kmead.net.service)."""

from __future__ import annotations

import logging
from typing import Any

from kmea.maps.files import MarkerMap
from kmea.pipeline import Pipeline
from kmead.config.startup import EXIT_RUNTIME, StartupError
from kmead.net.service import Service
from kmead.outputs.robots import RobotSender

__all__ = ["ExtraOutputs"]

log = logging.getLogger("kmead")


class ExtraOutputs(Service):
    """Zenoh and Foxglove, opened by :meth:`_start_zenoh` and :meth:`_start_foxglove`."""

    # The daemon's, opened before these.
    pipeline: Pipeline
    world_map: MarkerMap
    source_spec: str
    robots: RobotSender
    zenoh: Any  # kmead.outputs.zenoh.ZenohOutput when [zenoh] enabled = true
    zenoh_camera: Any  # kmead.outputs.zenoh_camera.ZenohCamera, with it
    foxglove: Any  # kmead.viewers.foxglove.FoxgloveServer when [foxglove] enabled = true

    def _start_zenoh(self) -> None:
        """Robot poses on Zenoh (docs/ros2.md): the relay hands it every message."""
        try:
            from kmead.outputs.zenoh import ZenohOutput
        except ImportError:
            raise StartupError("key 'zenoh.enabled': the zenoh extra is not installed "
                               "(pip install 'kmea[zenoh]')") from None
        from kmead.outputs.zenoh_camera import DuplicateCamera, ZenohCamera, camera_id

        z = self.cfg["zenoh"]
        self.zenoh = ZenohOutput.open(z)
        self.closing.callback(self._close_zenoh)
        self.relay.sink = self.zenoh.send
        # This kmead as a camera of its site, for the fusion nodes (docs/fusion.md), and
        # one of the robots' possible voices (kmead.outputs.voice).
        relay = self.relay
        try:
            self.zenoh_camera = ZenohCamera(
                self.zenoh.session, z["site"], camera_id(z, self.source_spec),
                self._camera_meta(), known=lambda name: name in relay.channels,
                on_quiet=self.zenoh.quiet, event=self.event)
        except DuplicateCamera as e:
            relay.muted = True  # it never spoke: its close tells the robots nothing
            raise StartupError(str(e)) from None
        self.closing.callback(self._close_zenoh_camera)
        self.relay.voice = self.zenoh_camera.voice
        self.robots.camera = self.zenoh_camera

    def _camera_meta(self) -> dict:
        from kmead.outputs.zenoh_camera import camera_id, meta_body

        return meta_body(camera_id(self.cfg["zenoh"], self.source_spec), self.world_map,
                         self.pipeline.camera, self.source_spec, self.cfg["camera"]["file"])

    def _start_foxglove(self) -> None:
        fx = self.cfg["foxglove"]
        try:
            from kmead.viewers.foxglove import FoxgloveServer
        except ImportError:
            raise StartupError("key 'foxglove.enabled': the foxglove extra is not installed "
                               "(pip install 'kmea[foxglove]')") from None
        try:
            self.foxglove = FoxgloveServer(self.world_map, self.pipeline.camera, fx["host"],
                                           fx["port"], fx["image_hz"])
        except OSError as e:
            raise StartupError(f"key 'foxglove.port': {e}; another kmead is probably running "
                               "(or set foxglove.port = 0 for a free port)",
                               EXIT_RUNTIME) from None
        self.closing.callback(self.foxglove.close)
        log.info("foxglove: serving %s (open it in Foxglove: Open connection, "
                 "Foxglove WebSocket)", self.foxglove.url)

    def _close_zenoh_camera(self) -> None:
        if self.zenoh_camera is not None:
            self.zenoh_camera.close()
            self.zenoh_camera = None
            self.robots.camera = None

    def _close_zenoh(self) -> None:
        if self.zenoh is not None:
            log.info("zenoh: %d messages published, %d failed", self.zenoh.sent,
                     self.zenoh.errors)
            self.zenoh.close()
            self.zenoh = None
