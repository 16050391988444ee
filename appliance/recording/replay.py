"""Replay: measure a recorded test again from its recorded pixels.

`replay_recording` reads a recording (`appliance.recording.reader`), rebuilds the test's
tracker and gauges from the recorded configuration, reference frame and marks, and measures
every recorded frame again with the same per-frame code as the live loop
(`appliance.measure.frame_measurer.FrameMeasurer`), on a frame rebuilt from the recorded windows
(`appliance.measure.frame_windows.paste_windows`) with the recorded controller state and device
time. Zero commands are applied where they were recorded.

Without an override this reproduces the recorded strain series bit for bit; the summary
says so with `max_abs_diff_to_recorded` (largest difference of the axial engineering strain:
0.0 when exact; infinite, null in JSON, when it is NaN on one side only) and
`samples_differing` (samples in which any recorded quantity differs: strains, elongation,
gauge length, Poisson's ratio, data-valid flag). With an
override (`--config FILE`: `[tracking]` keys replacing the recorded ones, e.g. another subset
size or search) the test is measured again; pixels the new tracking needs but the recording
does not hold read as zero, and `frames_reading_unrecorded_pixels` counts the frames where
that happened. The points and their marks always come from the recording, so an override of
any other table (`[gauge] length_mm`, the camera, the optics' lens keys, ...) cannot be
applied and is refused in one line naming it, never silently ignored.

The recording measures with the calibration it was measured with: the whole calibration
document is recorded (`appliance.recording.calibration_record`), so a replay of a test measured
in the object plane measures in it again, bit for bit, without the file. An override's
`[optics] calibration = "FILE"` (relative to the override file's directory) is applied as
post-processing: the recorded marks are measured in the object plane of FILE instead (a
calibration made for another image size is refused in one line); `calibration = ""` measures
them by the recorded nominal scale. The summary names the calibration measured with.

The file is read whole once before anything is measured, so a file that cannot be replayed
(not one extensometer recording, its configuration or marks unreadable, its reference frame
lost) is refused in one line naming it, with the damage when there is some. A truncated or
corrupted file replays up to the damage (`appliance.recording.reader`): the summary's `damage`
says where, `recorded_samples` how many samples the recording holds (when its end was read).
When the `reference.png` attachment is damaged or missing, the reference frame is read from
the `/camera/full` frame recorded with it (`reference_frame` says which); the file is still
reported as damaged.

The replay's exit status is its own (completed, or damaged). Its outputs (the report, a
viewer) follow the test as recorded: when the recording's `run_stop` says the specimen broke
and every recorded sample was measured again, they see the test end at its break, so the
report determines the results that need the fracture as the run did.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from appliance.config import Config, config_from_table, merge_tables, read_config_table
from appliance.errors import InputError
from appliance.measure.frame_measurer import FrameMeasurer, StrainSample, tracker_and_gauges
from appliance.measure.frame_windows import paste_windows, uncovered
from appliance.measure.gauges import Calibration, Gauge, StrainGaugesLayout
from appliance.recording.calibration_record import (
    recorded_calibration,
    recorded_nominal_scale,
)
from appliance.recording.format import (
    REFERENCE_ATTACHMENT,
    STRAIN_FIELDS,
    TOPIC_FULL,
    FormatError,
    image_of,
    image_of_png,
    machine_of,
    number,
    window_of,
)
from appliance.recording.reader import (
    RecordedSample,
    RecordingReader,
    config_table,
    recorded_devices,
    run_facts,
)
from appliance.run.loop import LoopResult
from appliance.run.object_plane import (
    calibration_facts,
    calibration_file,
    check_image_size,
    out_of_plane_bound,
    resolved_calibration_path,
)
from appliance.run.outputs import RunFacts, RunOutput
from appliance.run.state import ExitStatus
from appliance.run.summary import RunOutcome, RunSummary, SampleRecord
from hal.camera.base import Frame


@dataclass(frozen=True)
class _Setup:
    facts: RunFacts
    measurer: FrameMeasurer
    shape: tuple[int, int]
    dtype: np.dtype
    reference_source: str


REPLAYABLE_TABLES = ("tracking",)
"""The configuration tables a replay can apply: how the recorded pixels are measured."""

_WHY_NOT_REPLAYABLE = {
    "gauge": "the marks were placed when the test ran, and only the pixels around them recorded",
    "camera": "the frames are recorded as they were taken",
    "trigger": "the frames are recorded as they were taken",
    "optics": "the recorded calibration gives the scale; only calibration can be replaced",
    "machine": "the machine's readings are recorded",
    "sim": "the simulated world's frames are recorded",
    "run": "a replay measures every recorded sample",
    "rerun": "a replay's viewer is set with --rerun-serve, --rerun-connect or --rerun-save",
}


def _checked_override(path: Path) -> dict:
    """The override file's tables; InputError naming the first table or key a replay cannot
    apply (every key outside `REPLAYABLE_TABLES`)."""
    table = read_config_table(path)
    for section, keys in table.items():
        if section in REPLAYABLE_TABLES:
            continue
        if section == "optics" and isinstance(keys, dict) and set(keys) == {"calibration"}:
            continue
        why = _WHY_NOT_REPLAYABLE.get(section, "a replay does not use it")
        named = [k for k in keys if k != "calibration"] if isinstance(keys, dict) else []
        key = f" {named[0]}" if named else ""
        raise InputError(f"{path}: [{section}]{key}: cannot be applied to a replay ({why})")
    return table


def _setup(reader: RecordingReader, override: Path | None) -> _Setup:
    """What measures the recording again, from what the whole file read said; InputError
    naming the file when it is not a replayable recording (with the damage, if any)."""
    if reader.meta("recording") is None and reader.damages:
        raise InputError(f"{reader.path}: nothing to replay: {reader.describe_damage()}")
    reader.check_format()
    try:
        return _built(reader, override)
    except InputError as exc:
        damage = reader.describe_damage()
        if damage is None:
            raise
        raise InputError(f"{exc} ({damage})") from None


def _built(reader: RecordingReader, override: Path | None) -> _Setup:
    table = config_table(reader)
    if override is not None:
        table = merge_tables(table, _checked_override(override))
    config = config_from_table(table, str(override) if override else f"{reader.path} (config)")
    start = reader.require("run_start")
    calibration_meta = reader.require("calibration")
    marks_meta = reader.require("marks")
    try:
        reference_image, reference_source = _reference_image(reader, start)
        points = np.array(json.loads(marks_meta["points"]), dtype=np.float64)
        axial = json.loads(marks_meta["axial"])
        transverse = json.loads(marks_meta["transverse"])
        layout = StrainGaugesLayout(
            Gauge(tuple(axial[0]), tuple(axial[1])),
            None if transverse is None else Gauge(tuple(transverse[0]), tuple(transverse[1])),
        )
        marks = tuple(tuple(int(k) for k in mark) for mark in json.loads(marks_meta["marks"]))
        calibration = _calibration(reader, config, calibration_meta, override, start)
        reference = Frame(
            image=reference_image,
            frame_id=int(start["reference_frame_id"]),
            timestamp_ns=int(start["reference_timestamp_ns"]),
            exposure_us=float(start["reference_exposure_us"]),
        )
        epoch_offset_ns = int(start["epoch_offset_ns"])
    except (KeyError, ValueError, TypeError, IndexError, OverflowError, FormatError) as exc:
        raise InputError(
            f"{reader.path}: the recorded run facts are not readable ({exc})"
        ) from None
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputError(f"{reader.path}: the recorded points are not an (n, 2) array")
    try:
        tracker, gauges = tracker_and_gauges(
            config.tracking, reference_image, points, layout, calibration, config.gauge.marks
        )
    except (ValueError, TypeError, IndexError) as exc:
        raise InputError(f"{reader.path}: the recorded marks cannot be tracked ({exc})") from None
    facts = RunFacts(
        config=config,
        reference=reference,
        points=points,
        marks=marks,
        layout=layout,
        calibration=calibration,
        gauge_length_mm=gauges.gauge_length_mm,
        epoch_offset_ns=epoch_offset_ns,
        devices=recorded_devices(reader),
        facts=run_facts(reader),
    )
    measurer = FrameMeasurer(tracker, gauges, reference.timestamp_ns)
    return _Setup(facts, measurer, reference_image.shape, reference_image.dtype, reference_source)


def _calibration(
    reader: RecordingReader,
    config: Config,
    record: dict[str, str],
    override: Path | None,
    start: dict[str, str],
) -> Calibration:
    """The recorded calibration; or the override's `[optics] calibration` (a file, or ""
    for the recorded nominal scale), checked against the recorded image size."""
    if override is None or "calibration" not in read_config_table(override).get("optics", {}):
        return recorded_calibration(record, str(reader.path))
    if not config.optics.calibration:
        return Calibration(recorded_nominal_scale(record))
    calibration = calibration_file(resolved_calibration_path(config, override))
    assert calibration is not None
    check_image_size(calibration, int(start["image_width"]), int(start["image_height"]))
    return calibration


def _reference_image(reader: RecordingReader, start: dict[str, str]) -> tuple[np.ndarray, str]:
    """The reference frame's image and where it was read: the `reference.png` attachment, or,
    when that is damaged or missing, the `/camera/full` frame recorded with it (sequence 0 at
    the reference's acquisition time, of the recorded size). InputError when neither is
    readable."""
    data = reader.attachments.get(REFERENCE_ATTACHMENT)
    if data is not None:
        try:
            return image_of_png(data), REFERENCE_ATTACHMENT
        except FormatError as exc:
            why = f"not readable ({exc})"
    elif REFERENCE_ATTACHMENT in reader.damaged_attachments:
        why = "damaged (it fails its CRC)"
    elif "" in reader.damaged_attachments:
        why = "damaged (its record is not readable)"
    else:
        why = "missing"
    recorded = reader.reference_full_frame
    taken_ns = int(start["epoch_offset_ns"]) + int(start["reference_timestamp_ns"])
    size = (int(start["image_height"]), int(start["image_width"]))
    if recorded is not None and recorded[0] == taken_ns:
        try:
            image = image_of(recorded[1])
        except FormatError:
            image = None
        if image is not None and image.shape == size and str(image.dtype) == start["image_dtype"]:
            return image, TOPIC_FULL
    raise InputError(
        f"{reader.path}: the reference frame cannot be recovered: the {REFERENCE_ATTACHMENT} "
        f"attachment is {why}, and no {TOPIC_FULL} frame recorded with it was read"
    )


def _frame_of(setup: _Setup, recorded: RecordedSample, path: Path):
    points = recorded.points
    try:
        windows = [
            window_of(recorded.windows[int(place["mark"])], place) for place in points["windows"]
        ]
        image = paste_windows(setup.shape, setup.dtype, windows)
        frame = Frame(
            image=image,
            frame_id=int(points["frame_id"]),
            timestamp_ns=int(points["timestamp_ns"]),
            exposure_us=number(points["exposure_us"]),
        )
        machine = machine_of(recorded.machine) if recorded.machine is not None else None
    except (KeyError, ValueError, TypeError, FormatError) as exc:
        raise InputError(f"{path}: sample {recorded.index} is not readable ({exc})") from None
    return frame, machine, windows


def _same(mine: float, theirs: float) -> bool:
    return mine == theirs or (math.isnan(mine) and math.isnan(theirs))


def _compare(sample: StrainSample, recorded: dict[str, Any]) -> tuple[float, bool]:
    """(|engineering strain - recorded|, whether any recorded quantity differs)."""
    differs = bool(recorded.get("data_valid")) != sample.data_valid
    for name in STRAIN_FIELDS:
        differs |= not _same(float(getattr(sample.reading, name)), number(recorded.get(name)))
    mine = sample.reading.engineering_strain
    theirs = number(recorded.get("engineering_strain"))
    if _same(mine, theirs):
        return 0.0, differs
    return abs(mine - theirs) if math.isfinite(mine - theirs) else math.inf, differs


def replay_recording(
    path: str | Path,
    *,
    override: Path | None = None,
    outputs: Sequence[RunOutput] = (),
    progress: TextIO | None = None,
) -> RunOutcome:
    """Measure a recording again; see the module docstring.

    Args:
        path: the recording.
        override: a TOML file whose tables and keys replace the recorded configuration's;
            only `REPLAYABLE_TABLES` (how the pixels are measured) can be applied.
        outputs: outputs following the replay as they would a live test (a viewer).
        progress: a terminal stream for a progress line; None = quiet.

    Raises:
        InputError: the file is not a readable recording, or the override is bad or cannot be
            applied to a replay (one line naming its table and key).
    """
    path = Path(path)
    if override is not None:
        _checked_override(override)
    reader = RecordingReader(path)
    try:
        reader.read_all()
        setup = _setup(reader, override)
        return _replay(reader, setup, override, outputs, progress)
    finally:
        reader.close()


def _replay(
    reader: RecordingReader,
    setup: _Setup,
    override: Path | None,
    outputs: Sequence[RunOutput],
    progress: TextIO | None,
) -> RunOutcome:
    for output in outputs:
        output.begin(setup.facts)
    records: list[SampleRecord] = []
    latencies: list[float] = []
    tracking_time = 0.0
    worst = 0.0
    differing = 0
    unrecorded = 0
    samples = reader.samples()
    for recorded in samples:
        frame, machine, windows = _frame_of(setup, recorded, reader.path)
        if recorded.points.get("zeroed"):
            setup.measurer.zero()
        started = time.perf_counter()
        sample = setup.measurer.measure(
            frame, machine, started, int(recorded.strain.get("frames_dropped", 0))
        )
        tracking_time += time.perf_counter() - started
        latencies.append(sample.latency_s)
        if uncovered([w.region for w in sample.windows], windows):
            unrecorded += 1
        difference, differs = _compare(sample, recorded.strain)
        worst = max(worst, difference)
        differing += differs
        truth = recorded.truth or {}
        records.append(
            SampleRecord.of(
                sample,
                number(truth.get("true_engineering_strain")),
                number(truth.get("true_elongation_mm")),
            )
        )
        for output in outputs:
            output(sample)
        if progress is not None:
            progress.write(
                f"\r  sample {sample.index:6d}  strain "
                f"{sample.reading.engineering_strain * 100:9.3f} %"
            )
            progress.flush()
    if progress is not None:
        progress.write("\n")
    stop = reader.meta("run_stop") or {}
    damage = reader.describe_damage()
    recorded_samples = _recorded_samples(stop)
    if recorded_samples is None:
        notes = [f"{len(records)} recorded samples measured before it"]
    else:
        notes = [f"{len(records)} of {recorded_samples} recorded samples measured"]
    if setup.reference_source != REFERENCE_ATTACHMENT:
        notes.append(f"the reference frame was read from {setup.reference_source}")
    result = LoopResult(
        exit_status=ExitStatus.DAMAGED if damage else ExitStatus.COMPLETED,
        reason="; ".join([damage, *notes]) if damage else "every recorded sample measured",
        frames_processed=len(records),
        frames_dropped=_count(stop.get("frames_dropped")) or 0,
        latencies_s=latencies,
        tracking_time_s=tracking_time,
    )
    for output in outputs:
        output.end(_as_recorded(result, stop))
    extra = {
        **{k: v for k, v in setup.facts.facts.items() if k != "test_id"},
        **_calibration_facts(setup),
        "recording": str(reader.path),
        "override": str(override) if override is not None else None,
        "recorded_exit_status": stop.get("exit_status"),
        "recorded_reason": stop.get("reason"),
        "recorded_samples": recorded_samples,
        "reference_frame": setup.reference_source,
        "max_abs_diff_to_recorded": worst if records else None,
        "samples_differing": differing,
        "frames_reading_unrecorded_pixels": unrecorded,
        "damage": damage,
    }
    for output in outputs:
        extra.update(output.stats())
    return RunOutcome(RunSummary.from_run(result, records), extra)


def _as_recorded(result: LoopResult, stop: dict[str, str]) -> LoopResult:
    """The replay's end as its outputs see it: a test the recording says broke ended at its
    break, when every recorded sample was measured again (the test's results that need the
    fracture, A, TS and Eb, are then determined as in the run); otherwise the replay's own."""
    if result.exit_status is ExitStatus.COMPLETED and stop.get("exit_status") == ExitStatus.BREAK:
        return replace(result, exit_status=ExitStatus.BREAK)
    return result


def _calibration_facts(setup: _Setup) -> dict[str, Any]:
    """The calibration measured with, and its out-of-plane bound, as summary facts (the
    recorded ones, unless an override replaced the calibration)."""
    facts = setup.facts
    calibration = facts.calibration
    recorded = facts.facts
    if recorded.get("calibration_checksum") == (calibration.checksum or None) and (
        "measured_in" in recorded
    ):
        return {}
    distance = recorded.get("object_distance_mm")
    bound = out_of_plane_bound(
        calibration,
        float(distance) if isinstance(distance, (int, float)) else math.nan,
        facts.gauge_length_mm,
    )
    return {
        **calibration_facts(calibration),
        "scale_mm_per_px": calibration.scale_mm_per_px,
        **bound.facts(),
    }


def _count(text: str | None) -> int | None:
    return int(text) if text is not None and text.isdigit() else None


def _recorded_samples(stop: dict[str, str]) -> int | None:
    """The samples the recording says it holds (`run_stop`), None when its end was not read."""
    recorded = _count(stop.get("recording_samples"))
    return recorded if recorded is not None else _count(stop.get("frames_processed"))


def is_exact(outcome: RunOutcome) -> bool:
    """Whether a replay measured every recorded sample again to the same numbers."""
    return outcome.extra.get("samples_differing") == 0 and outcome.extra.get("damage") is None
