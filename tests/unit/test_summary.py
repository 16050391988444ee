"""Every count of the summary comes from the per-sample records, the strain file's rows."""

import math

from appliance.run.loop import LoopResult
from appliance.run.summary import RunSummary, SampleRecord


def _record(valid: bool, lost: int, updates: int = 0) -> SampleRecord:
    return SampleRecord(
        strain=0.01, elongation_mm=0.25, valid=valid, points_lost=lost, reference_updates=updates
    )


def test_lost_points_count_every_sample_and_apart_the_valid_ones():
    records = [_record(True, 0, 1), _record(True, 2), _record(False, 3), _record(False, 6, 1)]
    summary = RunSummary.from_run(LoopResult(frames_processed=len(records)), records)
    assert summary.lost_points == 11
    assert summary.lost_points_in_valid_samples == 2
    assert summary.invalid_samples == 2 and summary.reference_updates == 2
    assert summary.truth_final_strain is None and math.isclose(summary.final_strain, 0.01)


def test_a_run_whose_every_sample_is_invalid_has_no_final_strain():
    records = [_record(False, 4) for _ in range(5)]
    summary = RunSummary.from_run(LoopResult(frames_processed=5), records)
    assert summary.final_strain is None and summary.lost_points == 20
    assert summary.lost_points_in_valid_samples == 0 and summary.invalid_samples == 5
