"""The calibration a test was measured with, as its recording keeps it.

The `extensometer.calibration` metadata record (every value a string):

    scale_mm_per_px    the scale measured with (by nominal scale), or the calibration's scale
                       at the image centre (in the object plane), repr of a float
    gauge_length_mm    the original axial gauge length L0, mm, repr of a float
    measured_in        "nominal scale" or "object plane"       (format 1 recordings: absent,
                                                                 read as "nominal scale")
    file               the calibration file's path when the test ran ("" when none)
    checksum           the calibration's checksum ("sha256:<hex>"; "" when none)
    document           the whole calibration file as JSON, its checksum included ("" when none)
    nominal_scale_mm_per_px   the thin-lens scale of the optics (object plane only)

A replay measures with the recorded document (checked against its checksum), so it needs
neither the file nor the machine it was made on.
"""

from __future__ import annotations

import json
import math

from appliance.errors import InputError
from appliance.measure.gauges import Calibration
from appliance.optics.calibration_file import calibration_from_document
from appliance.run.outputs import RunFacts

OBJECT_PLANE = "object plane"
NOMINAL_SCALE = "nominal scale"


def calibration_metadata(facts: RunFacts) -> dict[str, str]:
    """The `calibration` metadata record of a test."""
    calibration = facts.calibration
    record = {
        "scale_mm_per_px": repr(calibration.scale_mm_per_px),
        "gauge_length_mm": repr(facts.gauge_length_mm),
        "measured_in": OBJECT_PLANE if calibration.in_object_plane else NOMINAL_SCALE,
        "file": calibration.file,
        "checksum": calibration.checksum,
        "document": "",
    }
    if calibration.camera is not None:
        document = calibration.camera.to_document()
        document["checksum"] = calibration.camera.checksum
        record["document"] = json.dumps(document, sort_keys=True)
    nominal = facts.facts.get("nominal_scale_mm_per_px")
    if nominal is not None:
        record["nominal_scale_mm_per_px"] = repr(float(nominal))
    return record


def recorded_calibration(record: dict[str, str], source: str) -> Calibration:
    """What the recorded test was measured with; `source` names the recording in errors.

    Raises:
        InputError: a scale or calibration document that cannot be read, or a document that
            fails its checksum.
    """
    try:
        scale = float(record["scale_mm_per_px"])
    except (KeyError, ValueError):
        raise InputError(f"{source}: the recorded scale is not readable") from None
    text = record.get("document", "")
    if not text:
        return Calibration(scale)
    try:
        document = json.loads(text)
    except ValueError:
        raise InputError(f"{source}: the recorded calibration is not readable") from None
    camera = calibration_from_document(document, f"{source} (recorded calibration)")
    return Calibration.object_plane(camera, record.get("file", ""))


def recorded_nominal_scale(record: dict[str, str]) -> float:
    """The thin-lens scale of the recorded test, mm/px (NaN when it was not recorded)."""
    text = record.get("nominal_scale_mm_per_px")
    if text is None:
        return float(record.get("scale_mm_per_px", "nan"))
    try:
        return float(text)
    except ValueError:
        return math.nan
