"""A simulated test places its gauge on the specimen it detects in the reference frame and says
so: the summary and the recording carry the placement, where it went and the gauge length the
marks achieve; a gauge longer than the detected parallel length is refused before the start."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config import config_from_table
from appliance.errors import InputError
from appliance.recording.reader import RecordingReader, run_facts
from appliance.runner import OutputFiles, run_test
from appliance.sim.world import PRESETS, SimWorld


def _config(**gauge):
    return config_from_table(
        {
            "sim": {"material": "rubber"},
            "run": {"until_strain": 0.02, "until_break": False},
            "gauge": gauge,
        }
    )


def test_the_summary_and_the_recording_say_how_the_gauge_was_placed(tmp_path):
    config = _config()
    recording = tmp_path / "test.mcap"
    outcome = run_test(
        config, simulate=True, files=OutputFiles.in_directory(tmp_path / "out", recording)
    )
    facts = outcome.as_dict()
    assert facts["gauge_placement"] == "detected"
    assert facts["gauge_length_achieved_mm"] == pytest.approx(25.0, rel=1e-9)
    truth = SimWorld.from_config(config, PRESETS["rubber"].optics).specimen_centre_px
    assert np.hypot(*np.subtract(facts["gauge_centre_px"], truth)) < 1.0
    width_px = 6.2 / PRESETS["rubber"].optics.scale_mm_per_px
    assert facts["specimen_width_px"] == pytest.approx(width_px, abs=0.2)
    reader = RecordingReader(recording)
    try:
        reader.read_all()
        recorded = run_facts(reader)
    finally:
        reader.close()
    assert recorded["gauge_placement"] == "detected"
    assert recorded["gauge_length_achieved_mm"] == facts["gauge_length_achieved_mm"]


def test_a_gauge_longer_than_the_parallel_length_is_refused_before_the_start():
    with pytest.raises(InputError, match=r"^\[gauge\] length_mm: the marks span .* parallel"):
        run_test(_config(length_mm=40.0), simulate=True)
