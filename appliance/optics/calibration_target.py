"""A calibration target: its geometry in its own plane, and finding its corners in an image.

Three kinds, each `COLS x ROWS` and one pitch `square_mm`:

- ``charuco``: a ChArUco board (OpenCV's `CharucoBoard`): COLS x ROWS chessboard squares,
  an ArUco marker of side `marker_mm` (dictionary `dictionary`) in every white square. Its
  inner corners are identified by the markers, so a view that shows only part of the board
  still counts (the field's edges and corners can be reached).
- ``chessboard``: COLS x ROWS squares; the (COLS-1) x (ROWS-1) inner corners must all be
  visible, with a white quiet zone of at least one square around the board.
- ``circles``: a symmetric grid of COLS x ROWS dark circles on white, centre spacing
  `square_mm`, diameter half the spacing (`CIRCLE_DIAMETER_FRACTION`), all visible. The
  grid is symmetric (not OpenCV's asymmetric grid): a view turned by 180 degrees numbers the
  circles from the other end, which changes the target's frame in that view but neither the
  intrinsics nor the scale. The centre of a tilted circle's image is not the image of its
  centre: on the simulated bench (7 mm circles at 400 mm, tilted 32..40 degrees) the detected
  centres lie 0.08..0.10 px RMS from the truth, a bias the calibration absorbs into each
  view's pose.

Target frame (OpenCV's ChArUco convention, shared by all three): origin at the board's top-left
corner (the outer corner of the first square; for circles, one spacing up and left of the
first circle's centre), X along the columns, Y along the rows, Z = 0 on the printed surface:
inner corner (row i, column j) of a board is at ``((j + 1) s, (i + 1) s)``, circle (i, j) at
``((j + 1) s, (i + 1) s)``. Corner ids number them row by row from 0. The board's thickness
is taken as zero: its plane is its printed surface.

Detection (8-bit grey image):

- charuco: `cv2.aruco.CharucoDetector` (markers, then the chessboard corners they identify),
  refined by `cv2.cornerSubPix` over a window of a tenth of the corners' spacing (OpenCV's
  own refinement leaves some corners 0.1 px off on steeply tilted views), then by fitting a
  model of the blurred corner to the pixels within 0.9 of the square-to-marker gap of it
  (`appliance.optics.chessboard_corner_fit`: `cornerSubPix` is biased towards the pixel
  grid by about 0.013 px RMS); a view is found when at least `MIN_CORNERS` corners are.
- chessboard: `cv2.findChessboardCornersSB` with `CALIB_CB_EXHAUSTIVE | CALIB_CB_ACCURACY`
  (the sector-based detector: subpixel corners by fitting the image around each, more accurate
  than `findChessboardCorners` + `cornerSubPix`), then the blurred corner's model fitted over
  the pixels within a quarter square of each corner (its corners 0.014..0.05 px RMS per
  coordinate from the truth on the simulated views, the fit's 0.001..0.002 px).
- circles: `cv2.findCirclesGrid` with `CALIB_CB_SYMMETRIC_GRID` and a blob detector accepting
  circles of 20 px^2 up to a tenth of the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from appliance.optics.chessboard_corner_fit import fit_chessboard_corners

FloatArray = npt.NDArray[np.float64]

KINDS = ("charuco", "chessboard", "circles")
MIN_CORNERS = 8
CIRCLE_DIAMETER_FRACTION = 0.5
DEFAULT_DICTIONARY = "DICT_5X5_100"
DEFAULT_MARKER_FRACTION = 0.7
CHESSBOARD_WINDOW_FRACTION = 0.25
"""A chessboard corner's fitting window reaches this fraction of a square from it."""
CHARUCO_WINDOW_FRACTION = 0.9
"""A ChArUco corner's fitting window reaches this fraction of the gap between a square's edge
and its marker (the marker's nearest point lies 1.41 gaps from the corner)."""


@dataclass(frozen=True)
class Detection:
    """The target's corners found in one image.

    Attributes:
        ids: corner ids (n,), indices into `CalibrationTarget.object_points_mm`.
        image_px: their pixel positions (n, 2), column, row.
    """

    ids: npt.NDArray[np.int64]
    image_px: FloatArray

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class CalibrationTarget:
    """A planar calibration target.

    Attributes:
        kind: "charuco", "chessboard" or "circles".
        columns, rows: squares across and down (circles: circles across and down).
        square_mm: square side (circles: centre spacing), mm.
        marker_mm: ChArUco marker side, mm (0 = `DEFAULT_MARKER_FRACTION` of the square).
        dictionary: ChArUco marker dictionary, an OpenCV name such as "DICT_5X5_100".

    Raises:
        ValueError: an unknown kind or dictionary, too few squares, a non-positive size, a
            marker not smaller than its square, or a dictionary with too few markers.
    """

    kind: str
    columns: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = DEFAULT_DICTIONARY

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"target kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        least = 2 if self.kind == "circles" else 3
        if self.columns < least or self.rows < least:
            raise ValueError(
                f"a {self.kind} target needs at least {least}x{least}, got "
                f"{self.columns}x{self.rows}"
            )
        if not (math.isfinite(self.square_mm) and self.square_mm > 0):
            raise ValueError(f"square size must be > 0 mm, got {self.square_mm}")
        if self.kind == "charuco":
            if not (math.isfinite(self.marker_mm) and 0 <= self.marker_mm < self.square_mm):
                raise ValueError(
                    f"marker size must be smaller than the square ({self.square_mm:g} mm), "
                    f"got {self.marker_mm:g} mm"
                )
            if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")
            markers = (self.columns * self.rows) // 2
            size = _dictionary(self.dictionary).bytesList.shape[0]
            if markers > size:
                raise ValueError(
                    f"a {self.columns}x{self.rows} ChArUco board needs {markers} markers, "
                    f"{self.dictionary} has {size}"
                )

    @property
    def marker_side_mm(self) -> float:
        """The ChArUco marker side in effect, mm."""
        return self.marker_mm or DEFAULT_MARKER_FRACTION * self.square_mm

    @property
    def grid_size(self) -> tuple[int, int]:
        """(columns, rows) of the corners (circles) detected: inner corners of a board."""
        if self.kind == "circles":
            return (self.columns, self.rows)
        return (self.columns - 1, self.rows - 1)

    @property
    def object_points_mm(self) -> FloatArray:
        """Every corner (circle centre) in the target frame, (n, 2) mm, row by row."""
        columns, rows = self.grid_size
        j, i = np.meshgrid(np.arange(columns), np.arange(rows))
        return np.column_stack([(j.ravel() + 1.0), (i.ravel() + 1.0)]) * self.square_mm

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the pattern, mm: the board's squares (circles: the grid with one
        spacing around it)."""
        extra = 1 if self.kind == "circles" else 0
        return ((self.columns + extra) * self.square_mm, (self.rows + extra) * self.square_mm)

    def charuco_board(self) -> Any:
        """OpenCV's `CharucoBoard` for a ChArUco target."""
        return cv2.aruco.CharucoBoard(
            (self.columns, self.rows),
            self.square_mm,
            self.marker_side_mm,
            _dictionary(self.dictionary),
        )

    def describe(self) -> str:
        """One line naming the target, as a user would order it."""
        text = f"{self.kind} {self.columns}x{self.rows}, {self.square_mm:g} mm"
        if self.kind == "charuco":
            text += f", markers {self.marker_side_mm:g} mm {self.dictionary}"
        return text

    def to_document(self) -> dict[str, Any]:
        """The target as the calibration file records it."""
        document: dict[str, Any] = {
            "kind": self.kind,
            "columns": self.columns,
            "rows": self.rows,
            "square_mm": self.square_mm,
        }
        if self.kind == "charuco":
            document["marker_mm"] = self.marker_side_mm
            document["dictionary"] = self.dictionary
        if self.kind == "circles":
            document["grid"] = "symmetric"
        return document

    def detect(self, image: npt.ArrayLike) -> Detection | None:
        """The target's corners in an 8-bit grey image, or None when it is not found (for
        ChArUco: fewer than `MIN_CORNERS` corners)."""
        grey = np.ascontiguousarray(image)
        if grey.dtype != np.uint8:
            raise ValueError(f"detection needs an 8-bit grey image, got {grey.dtype}")
        if self.kind == "charuco":
            return self._detect_charuco(grey)
        if self.kind == "chessboard":
            flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            found, corners = cv2.findChessboardCornersSB(grey, self.grid_size, flags=flags)
        else:
            found, corners = cv2.findCirclesGrid(
                grey,
                self.grid_size,
                flags=cv2.CALIB_CB_SYMMETRIC_GRID,
                blobDetector=_blob_detector(grey.shape),
            )
        if not found or corners is None:
            return None
        points = np.asarray(corners, np.float64).reshape(-1, 2)
        ids = np.arange(len(points), dtype=np.int64)
        if self.kind == "chessboard":
            jacobian = _plane_to_image(self.object_points_mm[ids], points)
            if jacobian is not None:
                radius_mm = CHESSBOARD_WINDOW_FRACTION * self.square_mm
                points, _ = fit_chessboard_corners(grey, points, jacobian, radius_mm)
        return Detection(ids, points)

    def _detect_charuco(self, grey: npt.NDArray[np.uint8]) -> Detection | None:
        detector = cv2.aruco.CharucoDetector(self.charuco_board())
        corners, ids, _, _ = detector.detectBoard(grey)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        ids = np.asarray(ids, np.int64).ravel()
        points = _refine_corners(grey, np.asarray(corners, np.float64).reshape(-1, 2))
        jacobian = _plane_to_image(self.object_points_mm[ids], points)
        if jacobian is not None:
            radius_mm = CHARUCO_WINDOW_FRACTION * 0.5 * (self.square_mm - self.marker_side_mm)
            points, _ = fit_chessboard_corners(grey, points, jacobian, radius_mm)
        order = np.argsort(ids)
        return Detection(ids[order], points[order])


def _refine_corners(grey: npt.NDArray[np.uint8], points: FloatArray) -> FloatArray:
    """`cv2.cornerSubPix` with a window of a tenth of the corners' spacing (3..15 px a side
    from the centre): wide enough to average noise, clear of the ArUco markers."""
    distances = np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(distances, np.inf)
    spacing_px = float(np.median(distances.min(axis=1)))
    half = int(np.clip(round(0.1 * spacing_px), 3, 15))
    refined = cv2.cornerSubPix(
        grey,
        points.astype(np.float32).reshape(-1, 1, 2),
        (half, half),
        (-1, -1),
        (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4),
    )
    return np.asarray(refined, np.float64).reshape(-1, 2)


def _plane_to_image(plane_mm: FloatArray, image_px: FloatArray) -> FloatArray | None:
    """The (n, 2, 2) Jacobian, px per mm, of the target plane's map to the image at each of
    the corners, from the homography of all of them (the lens's distortion changes it by a
    few per cent, enough for a fitting window); None when it cannot be found."""
    homography, _ = cv2.findHomography(plane_mm, image_px, 0)
    if homography is None or not np.all(np.isfinite(homography)):
        return None
    mapped = np.column_stack([plane_mm, np.ones(len(plane_mm))]) @ homography.T
    w = mapped[:, 2]
    if np.any(np.abs(w) < 1e-12):
        return None
    jacobian = np.empty((len(plane_mm), 2, 2))
    for i in range(2):
        for j in range(2):
            jacobian[:, i, j] = (homography[i, j] * w - mapped[:, i] * homography[2, j]) / w**2
    return jacobian


def _dictionary(name: str) -> Any:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _blob_detector(shape: tuple[int, ...]) -> Any:
    parameters = cv2.SimpleBlobDetector_Params()
    parameters.minArea = 20.0
    parameters.maxArea = 0.1 * shape[0] * shape[1]
    parameters.filterByConvexity = False
    parameters.filterByInertia = True
    parameters.minInertiaRatio = 0.3
    return cv2.SimpleBlobDetector_create(parameters)
