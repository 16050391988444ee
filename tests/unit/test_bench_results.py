"""A benchmark's report and figures in a results directory, and the directory's index."""

import json

from appliance import __version__
from appliance.bench.results import emit_figures, refresh_index, write_report


def test_a_report_says_what_was_run_when_and_where_and_the_index_lists_every_report(tmp_path):
    write_report(tmp_path, "speed", "Speed of the core", {"points_per_s": 123.0}, "| a | b |")
    emit_figures(
        "machine", "Reading the machine", {"reads": 7}, "reads  7", as_json=False, out=tmp_path
    )
    report = (tmp_path / "speed.md").read_text(encoding="utf-8").splitlines()
    assert report[0] == "# Speed of the core"
    assert report[2].startswith("- command: `") and report[3].startswith("- measured: ")
    assert f"extensometer {__version__}" in report[3] and " cores, " in report[4]
    assert report[-1] == "| a | b |"
    figures = json.loads((tmp_path / "speed.json").read_text(encoding="utf-8"))
    assert figures["figures"] == {"points_per_s": 123.0} and figures["host"]["cores"] >= 1
    assert "```\nreads  7\n```" in (tmp_path / "machine.md").read_text(encoding="utf-8")
    index = (tmp_path / "README.md").read_text(encoding="utf-8")
    assert "| [Reading the machine](machine.md) |" in index
    assert "| [Speed of the core](speed.md) |" in index
    (tmp_path / "notes.txt").write_text("not a report")
    refresh_index(tmp_path)
    rows = [line for line in (tmp_path / "README.md").read_text().splitlines() if "](" in line]
    assert len(rows) == 2
