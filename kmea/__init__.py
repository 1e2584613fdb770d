"""KMEA: marker-based localization of a camera and robots against a surveyed ArUco floor map.

Conventions used everywhere in the package:

* lengths in metres, angles in radians (degrees only in files meant for people);
* world frame: x right, y up (on the floor plan), z up from the floor;
* camera frame: OpenCV's (x right, y down, z forward along the optical axis);
* marker frame: OpenCV's ArUco frame (origin at the centre, x to the right edge,
  y to the top edge, z out of the printed face);
* a transform named ``a2b`` maps coordinates in frame ``a`` to frame ``b``.
"""

__version__ = "0.1.0"
