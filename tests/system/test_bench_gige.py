"""`extensometer bench gige` as a user runs it, on a small frame for a few seconds: the report's
frame counts add up and the strain it measured follows the camera's truth (its timings are
the benchmark's to judge, not this test's)."""

import json
import subprocess
import sys
from pathlib import Path

from appliance.bench.gige_rate import QUEUE_SIZE, STRAIN_AMPLITUDE
from tests.system.aravis_peers import needs_gige

pytestmark = needs_gige

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def test_a_short_gige_bench_accounts_for_every_frame_the_camera_delivered(tmp_path):
    out = tmp_path / "report"
    done = subprocess.run(
        [EXTENSOMETER, "bench", "gige", "--duration-s", "3", "--width-px", "256"]
        + ["--height-px", "256", "--frame-rate-hz", "50", "--json", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout)
    assert json.loads((out / "gige.json").read_text())["figures"] == figures
    assert "through the whole appliance" in (out / "gige.md").read_text()
    assert figures["exit_status"] == "stopped" and figures["reason"] == "benchmark over"
    frames = figures["frames"]
    accounted = frames["reference"] + frames["measured"] + frames["dropped_by_appliance"]
    assert frames["delivered"] == accounted + frames["not_measured_after_stop"]
    assert frames["dropped_by_appliance"] >= 0
    assert 0 <= frames["not_measured_after_stop"] <= QUEUE_SIZE + 2
    assert frames["drawn_by_camera"] >= frames["delivered"] + frames["lost_before_delivery"]
    assert frames["measured"] == frames["samples_seen_by_sinks"] == frames["valid_samples"] > 0
    assert figures["recording"]["samples"] == frames["measured"]
    assert figures["recording"]["full_frames"] >= 1
    assert figures["delivery_to_register_ms"]["n"] == frames["measured"]
    rates = figures["rates"]
    assert 0 < rates["measured_rate_hz"] <= rates["camera_rate_hz"]
    client = figures["client"]
    assert 0 < client["frames_seen"] <= frames["measured"] and client["requests"] > 0
    assert client["register_to_seen_ms"]["p50"] >= 0
    assert figures["max_abs_strain_error"] < 0.2 * STRAIN_AMPLITUDE
    assert (figures["verdict"] == "met") == (figures["verdict_reasons"] == [])
