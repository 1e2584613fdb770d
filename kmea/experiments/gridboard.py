"""Real photos of a known marker layout: leave-one-out marker errors of every estimator.

OpenCV's ArUco tutorial photographs a GridBoard of 5 x 7 markers (ids 0-34 row by row from
the top left, side 0.04 m, gaps 0.01 m) printed on paper, with a custom dictionary and
intrinsics that fit the photo only roughly. The board is a surveyed map: every detected
marker is estimated with itself left out of the references (as the paper evaluates) and
compared with its layout position. See ``../shared/README.md`` for the data.

World frame of the map: on the board plane z = 0, markers facing +z, x to the right along
the rows, y up the columns; origin marker 30 (bottom left), +X marker 34 (bottom right), +Y
marker 0 (top left), the same arrangement as the RobotAtFactory anchors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from kmea.estimators import get
from kmea.estimators.loo import loo_errors
from kmea.maps.files import Marker, MarkerMap
from kmea.pipeline import MarkerObserver
from kmea.vision.camera import CameraModel, load_camera
from kmea.vision.detection import MarkerDetector
from kmea.vision.dictionary import get_dictionary

__all__ = ["DEFAULT_DIR", "ESTIMATORS", "GridboardResult", "correcting_dictionary",
           "evaluate_image", "format_table", "gridboard_map", "main", "run_all"]

COLS, ROWS, LENGTH, GAP = 5, 7, 0.04, 0.01
# (label, registry name, options)
ESTIMATORS: tuple[tuple[str, str, dict], ...] = (
    ("kmea", "kmea", {}),
    ("lmea", "lmea", {}),
    ("umeyama", "umeyama", {}),
    ("kmea-robust", "kmea-robust", {}),
    ("corner-pnp fixed K", "corner-pnp", {"refine_intrinsics": False}),
    ("corner-pnp", "corner-pnp", {}),
)
IMAGES = ("gboriginal.png", "gbocclusion.png")


def gridboard_map() -> MarkerMap:
    """The tutorial GridBoard as a map (see the module docstring for the frame)."""
    pitch = LENGTH + GAP
    origin = np.array([LENGTH / 2, -((ROWS - 1) * pitch + LENGTH / 2), 0.0])
    markers = {}
    for i in range(COLS * ROWS):
        r, c = divmod(i, COLS)
        centre = np.array([c * pitch + LENGTH / 2, -(r * pitch + LENGTH / 2), 0.0]) - origin
        markers[i] = Marker(i, centre, np.eye(3), LENGTH)
    return MarkerMap(markers, dictionary="tutorial_dict.yml", default_length=LENGTH,
                     origin_id=30, x_id=34, y_id=0, name="OpenCV tutorial GridBoard 5x7",
                     source="<kmea.experiments.gridboard>")


@dataclass
class GridboardResult:
    """Leave-one-out errors (m, floor-plane distance) of one estimator on one photo."""

    image: str
    label: str
    errors: dict[int, float] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @property
    def mean(self) -> float:
        return float(np.mean(list(self.errors.values()))) if self.errors else float("nan")

    @property
    def median(self) -> float:
        return float(np.median(list(self.errors.values()))) if self.errors else float("nan")

    @property
    def worst(self) -> float:
        return float(max(self.errors.values())) if self.errors else float("nan")


def correcting_dictionary(path: Path) -> cv2.aruco.Dictionary:
    """The tutorial dictionary with the error correction its codes allow.

    The file gives no ``maxCorrectionBits`` (so 0: any flipped bit loses the marker, and the
    annotated ``gbocclusion.png``, whose drawn outlines cross the borders, yields 3 markers).
    Its 35 codes are at least 14 bits apart under rotation, so up to (14 - 1) // 2 = 6 bits
    are correctable unambiguously, the rule OpenCV's predefined dictionaries follow; the
    detector's ``errorCorrectionRate`` (0.6) then uses 3 of them.
    """
    d = get_dictionary(path)
    n = d.bytesList.shape[0]
    bits = [cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[i:i + 1], d.markerSize)
            for i in range(n)]
    dmin = min(int(np.count_nonzero(bits[i] != np.rot90(bits[j], r)))
               for i in range(n) for j in range(n) for r in range(4) if i != j or r)
    return cv2.aruco.Dictionary(d.bytesList, d.markerSize, max(0, (dmin - 1) // 2))


def evaluate_image(image: Path, dictionary: Path, camera: CameraModel,
                   estimators: tuple[tuple[str, str, dict], ...] = ESTIMATORS
                   ) -> tuple[list[GridboardResult], int]:
    """Detect, estimate per-marker poses, and score every estimator leave-one-out.

    Returns the results and the number of markers detected.
    """
    gray = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise FileNotFoundError(f"{image}: cannot read the image")
    world_map = gridboard_map()
    observer = MarkerObserver(MarkerDetector(dictionary=correcting_dictionary(dictionary)),
                              camera, world_map)
    ids, corners = observer.detect(gray)
    keep = [k for k, i in enumerate(ids.tolist()) if i in world_map]
    obs, _ = observer.poses(ids[keep], corners[keep])
    cam = camera.intrinsics
    results = []
    for label, name, options in estimators:
        est = get(name, **options)
        errors = loo_errors(est, obs, world_map, camera=cam)
        full = est.estimate(obs, world_map, camera=cam)
        info = {k: full.info[k] for k in ("fx", "fy", "k1", "reprojection_rms_px")
                if k in full.info}
        info["rejected"] = dict(full.rejected)
        results.append(GridboardResult(image.name, label, errors, info))
    return results, len(obs)


def run_all(data_dir: Path) -> list[GridboardResult]:
    """Every estimator on both tutorial photos in ``data_dir`` (``.../opencv-gridboard``)."""
    camera = load_camera(data_dir / "tutorial_camera_params.yml", image_size=(640, 480))
    out = []
    for name in IMAGES:
        out += evaluate_image(data_dir / name, data_dir / "tutorial_dict.yml", camera)[0]
    return out


def format_table(results: list[GridboardResult]) -> str:
    """A plain-text table in millimetres (for people)."""
    lines = [f"{'image':<16} {'estimator':<18} {'n':>3} {'mean mm':>8} {'median':>8} "
             f"{'max':>8}  notes"]
    for r in results:
        notes = []
        if "fx" in r.info:
            notes.append(f"fx {r.info['fx']:.1f} k1 {r.info['k1']:+.3f}")
        if r.info.get("rejected"):
            notes.append("rejected " + ",".join(str(i) for i in sorted(r.info["rejected"])))
        lines.append(f"{r.image:<16} {r.label:<18} {len(r.errors):>3} {r.mean * 1e3:>8.2f} "
                     f"{r.median * 1e3:>8.2f} {r.worst * 1e3:>8.2f}  {'; '.join(notes)}")
    return "\n".join(lines)


# Where the data lives next to a checkout: ../shared/data/opencv-gridboard.
DEFAULT_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "opencv-gridboard"


def main(argv: list[str] | None = None) -> int:
    """``python -m kmea.experiments.gridboard [DIR]``: print the table."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    data_dir = Path(args[0]) if args else DEFAULT_DIR
    if not (data_dir / "tutorial_camera_params.yml").is_file():
        print(f"gridboard: {data_dir}: no tutorial_camera_params.yml (give the "
              f"opencv-gridboard data directory)")
        return 2
    print(format_table(run_all(data_dir)))
    return 0


if __name__ == "__main__":  # pragma: no cover - manual use
    raise SystemExit(main())
