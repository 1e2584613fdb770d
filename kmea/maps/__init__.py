"""Marker maps: the model, files, the built-in floor, ArUco dictionary names, the survey."""
