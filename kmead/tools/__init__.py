"""Tools of the ``kmea`` command that need the daemon's parts (doctor, keys, snapshot; the
daemon's benchmarks are :mod:`kmead.benchmarks`)."""
