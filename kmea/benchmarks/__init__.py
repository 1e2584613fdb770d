"""The library's benchmarks behind ``kmea bench`` (they print figures; numpy and OpenCV
only, never kmead), and its dispatcher (:mod:`kmea.cli.bench`). The daemon's
benchmarks are in ``kmead/benchmarks/``."""
