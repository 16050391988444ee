"""`extensometer bench accuracy --quick` as a user runs it: a report with verdicts and plots."""

import json
import subprocess
import sys
from pathlib import Path

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def test_quick_accuracy_benchmark_writes_report_results_and_plots(tmp_path):
    out = tmp_path / "report"
    done = subprocess.run(
        [EXTENSOMETER, "bench", "accuracy", "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    results = json.loads((out / "accuracy.json").read_text())["figures"]
    assert {"a_tables", "b_blur", "b_stretch", "c_subset", "d_hard", "verdicts"} <= set(results)
    dense_float = [
        r
        for r in results["a_tables"]
        if r["pattern"] == "dense" and r["condition"] == "float" and r["prefilter_sigma"] > 0
    ]
    assert dense_float and all(abs(r["u_error"]["mean"]) < 0.002 for r in dense_float)
    report = (out / "accuracy.md").read_text()
    assert "## Targets" in report and "## Findings" in report
    for name in ("a_subpixel_error", "b_blur_success", "b_stretch_success", "c_subset_size"):
        assert (out / f"accuracy-{name}.png").stat().st_size > 10_000
    assert "verdicts:" in done.stdout
    assert "[Accuracy of the measurement core" in (out / "README.md").read_text()
