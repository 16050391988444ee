"""The printed summary: aligned `key value` lines, a missing fact as `-`."""

from __future__ import annotations

import io

from appliance.cli.printing import print_summary


class _Outcome:
    def as_dict(self) -> dict:
        return {"exit_status": "break", "final_strain": 5.989721234, "calibration_file": None}


def test_a_fact_the_run_does_not_have_shows_as_a_dash() -> None:
    stream = io.StringIO()
    print_summary(_Outcome(), stream)
    lines = stream.getvalue().splitlines()
    assert lines[0].split() == ["exit_status", "break"]
    assert lines[1].split() == ["final_strain", "5.98972"]
    assert lines[2].split() == ["calibration_file", "-"]
