"""`extensometer bench soak` as a user runs it: the shipped service, commanded over Modbus."""

import json
import subprocess
import sys
from pathlib import Path

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def test_a_short_soak_serves_commanded_tests_and_reports_the_service_per_test(tmp_path):
    out = tmp_path / "report"
    done = subprocess.run(
        [EXTENSOMETER, "bench", "soak", "--duration-s", "1", "--test-s", "2", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    figures = json.loads((out / "soak.json").read_text())["figures"]
    assert figures["viewer"] is True and figures["tests"] == 1
    (test,) = figures["per_test"]
    assert test["exit_status"] == 3
    assert test["frames"] > 0 and test["rss_mb"] > 0 and test["fds"] > 0 and test["threads"] > 0
    assert figures["rss_mb_per_test"] is None
    assert "goal met: no" in done.stdout and "[Soak" in (out / "README.md").read_text()
