"""Tools of the ``kmea`` command that need the daemon's parts (doctor, bench, keys,
snapshot)."""
