"""Frame sources: the interface (:mod:`.base`), files, cameras, the Pi camera, the simulator,
recordings, and the registry that opens one from a spec (:mod:`.registry`). Import from the
submodules: this package's ``__init__`` imports nothing, so a source module can import
:mod:`.base` without loading every other source."""
