"""A camera calibration as the appliance stores it: one JSON file with a checksum.

`extensometer calibrate` writes it; `run`, `serve`, `replay`, `camera-check` and `track` read
it (`[optics] calibration = "FILE"`, `--calibration FILE`), and every recording carries it in
its metadata so that a replay measures with the calibration the test was measured with.

The file (format 1), every length in mm, every image quantity in px:

    {
      "format": "extensometer-calibration",
      "format_version": 1,
      "camera": {"width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px",
                 "distortion": [k1, k2, p1, p2, k3], "telecentric": false},
      "plane": {"rotation_vector": [3], "translation_mm": [3]},
      "scale_mm_per_px": s,             # at the plane, at the image centre
      "scale_uncertainty_mm_per_px": u, # one standard uncertainty
      "rms_reprojection_px": e,
      "view_errors_px": [...],          # RMS reprojection error of each view
      "coverage_fraction": c,           # of the field covered by the target's corners
      "target": {...},                  # kind, size and squares of the target used
      "views": n,
      "software_version": "...", "created_utc": "...",
      "checksum": "sha256:<hex>"        # over the canonical JSON of every other key
    }

A file that is unreadable, foreign, of another format version, altered since it was written
(checksum), or made for another sensor size is refused with one line naming the file and the
reason (`InputError`).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance.errors import InputError
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection

FORMAT = "extensometer-calibration"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class CameraCalibration:
    """A calibrated camera and the specimen plane it looks at.

    Attributes:
        camera: intrinsics and lens distortion.
        plane: the specimen plane's pose in the camera frame.
        scale_mm_per_px: scale on the plane at the image centre, mm/px.
        scale_uncertainty_mm_per_px: its standard uncertainty, mm/px.
        rms_reprojection_px: RMS reprojection error over every corner of every view, px.
        view_errors_px: RMS reprojection error of each view, px.
        coverage_fraction: fraction of the field (0..1) the target's corners covered.
        target: the target used (kind, squares, square and marker size in mm, dictionary).
        software_version: the version of the software that made it.
        created_utc: when, ISO 8601 UTC.
    """

    camera: CameraModel
    plane: PlanePose
    scale_mm_per_px: float
    scale_uncertainty_mm_per_px: float = 0.0
    rms_reprojection_px: float = 0.0
    view_errors_px: tuple[float, ...] = ()
    coverage_fraction: float = 0.0
    target: Mapping[str, Any] = field(default_factory=dict)
    software_version: str = ""
    created_utc: str = ""

    def projection(self) -> PlaneProjection:
        """Pixels to millimetres on the specimen plane, and back."""
        return PlaneProjection(self.camera, self.plane)

    def to_document(self) -> dict[str, Any]:
        """The file's content without its checksum (JSON-ready)."""
        camera = self.camera
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "camera": {
                "width_px": camera.width_px,
                "height_px": camera.height_px,
                "fx_px": camera.fx_px,
                "fy_px": camera.fy_px,
                "cx_px": camera.cx_px,
                "cy_px": camera.cy_px,
                "distortion": [float(v) for v in camera.distortion.coefficients],
                "telecentric": camera.telecentric,
            },
            "plane": {
                "rotation_vector": list(self.plane.rotation_vector),
                "translation_mm": list(self.plane.translation_mm),
            },
            "scale_mm_per_px": self.scale_mm_per_px,
            "scale_uncertainty_mm_per_px": self.scale_uncertainty_mm_per_px,
            "rms_reprojection_px": self.rms_reprojection_px,
            "view_errors_px": list(self.view_errors_px),
            "coverage_fraction": self.coverage_fraction,
            "target": dict(self.target),
            "views": len(self.view_errors_px),
            "software_version": self.software_version,
            "created_utc": self.created_utc,
        }

    def to_json(self) -> str:
        """The file's text: the document with its checksum, indented."""
        document = self.to_document()
        document["checksum"] = checksum(document)
        return json.dumps(document, indent=2) + "\n"

    @property
    def checksum(self) -> str:
        """The checksum the file carries ("sha256:<hex>"): names this calibration."""
        return checksum(self.to_document())


def checksum(document: Mapping[str, Any]) -> str:
    """ "sha256:<hex>" of the canonical JSON (sorted keys, no spaces) of every key but
    "checksum"."""
    content = {key: value for key, value in document.items() if key != "checksum"}
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return "sha256:" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def save_calibration(calibration: CameraCalibration, path: Path) -> None:
    """Write `calibration` to `path` (JSON with its checksum).

    Raises:
        InputError: the file cannot be written (one line naming it).
    """
    try:
        Path(path).write_text(calibration.to_json(), encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{path}: cannot write the calibration ({exc.strerror or exc})") from None


def load_calibration(
    path: Path, *, sensor_size: tuple[int, int] | None = None
) -> CameraCalibration:
    """Read and check a calibration file.

    Args:
        path: the file.
        sensor_size: (width, height) px of the images it will be used on; None = not checked.

    Raises:
        InputError: one line naming the file and the reason: unreadable, not JSON, not a
            calibration, another format version, a checksum mismatch, a missing or bad value,
            or a calibration of another sensor size.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such calibration file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the calibration ({exc})") from None
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{path}: not a calibration file (not JSON: {exc.msg}, line {exc.lineno})"
        ) from None
    calibration = calibration_from_document(document, str(path))
    if sensor_size is not None and calibration.camera.sensor_size != tuple(sensor_size):
        made = "x".join(str(v) for v in calibration.camera.sensor_size)
        used = "x".join(str(v) for v in sensor_size)
        raise InputError(
            f"{path}: calibration made for a {made} px sensor, the images are {used} px "
            "(calibrate the camera with the region it measures with)"
        )
    return calibration


def calibration_from_document(document: Any, source: str) -> CameraCalibration:
    """A calibration from the file's parsed JSON (as read from a file or a recording's
    metadata); `source` names where it came from in the one-line error.

    Raises:
        InputError: as `load_calibration`.
    """
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise InputError(f'{source}: not a calibration file (no "format": "{FORMAT}")')
    if document.get("format_version") != FORMAT_VERSION:
        raise InputError(
            f"{source}: calibration format version {document.get('format_version')!r}, this "
            f"software reads version {FORMAT_VERSION}"
        )
    stated = document.get("checksum")
    try:
        actual = checksum(document)
    except ValueError:
        raise InputError(
            f"{source}: calibration holds a value that is not a finite number"
        ) from None
    if stated != actual:
        raise InputError(
            f"{source}: calibration checksum mismatch (the file was altered after it was written)"
        )
    try:
        camera = document["camera"]
        plane = document["plane"]
        model = CameraModel(
            int(camera["width_px"]),
            int(camera["height_px"]),
            float(camera["fx_px"]),
            float(camera["fy_px"]),
            float(camera["cx_px"]),
            float(camera["cy_px"]),
            LensDistortion.from_coefficients(camera["distortion"]),
            bool(camera.get("telecentric", False)),
        )
        pose = PlanePose.from_arrays(plane["rotation_vector"], plane["translation_mm"])
        calibration = CameraCalibration(
            camera=model,
            plane=pose,
            scale_mm_per_px=float(document["scale_mm_per_px"]),
            scale_uncertainty_mm_per_px=float(document.get("scale_uncertainty_mm_per_px", 0.0)),
            rms_reprojection_px=float(document.get("rms_reprojection_px", 0.0)),
            view_errors_px=tuple(float(v) for v in document.get("view_errors_px", ())),
            coverage_fraction=float(document.get("coverage_fraction", 0.0)),
            target=dict(document.get("target", {})),
            software_version=str(document.get("software_version", "")),
            created_utc=str(document.get("created_utc", "")),
        )
        calibration.projection()
    except KeyError as exc:
        raise InputError(f"{source}: calibration lacks the key {exc.args[0]}") from None
    except (TypeError, ValueError, IndexError) as exc:
        raise InputError(f"{source}: bad calibration value ({exc})") from None
    if not (math.isfinite(calibration.scale_mm_per_px) and calibration.scale_mm_per_px > 0):
        raise InputError(f"{source}: calibration scale_mm_per_px must be finite and > 0")
    return calibration
