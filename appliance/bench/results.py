"""Where a benchmark's figures go: stdout, and with `--out DIR` a report in a results directory.

Every benchmark prints its figures (a table, or JSON with `--json`). With `--out DIR` it also
writes

* `DIR/<name>.md`: its report, headed by what was run, when, and on what host (cores, CPU,
  Python, software version), then the figures as the benchmark presents them;
* `DIR/<name>.json`: every figure, for programs to read;

and refreshes `DIR/README.md`, the index of every report in DIR. The repository keeps the
reports of its reference host in `appliance/bench/results/` (written by
`extensometer bench NAME --out appliance/bench/results`); the manuals link there, so no
measured figure sits in prose where it would go stale. A benchmark's own extra files (plots,
per-case outputs) go beside its report, named after it.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import shlex
import sys
from pathlib import Path
from typing import Any

from appliance import __version__

INDEX = "README.md"
_HEADER = re.compile(r"^# (?P<title>.+)$|^- (?P<key>command|measured): (?P<value>.+)$")


def host_facts() -> dict[str, Any]:
    """The host the figures were measured on: cores, CPU model, Python, operating system."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cores": os.cpu_count(),
        "cpu": model,
        "python": platform.python_version(),
        "system": f"{platform.system()} {platform.release()}",
    }


def command_line() -> str:
    """The command that is running, as a user would type it."""
    program = Path(sys.argv[0]).name
    if program in ("extensometer", "__main__.py"):
        return shlex.join(["extensometer", *sys.argv[1:]])
    return shlex.join([program, *sys.argv[1:]])


def write_report(out: Path, name: str, title: str, figures: dict[str, Any], body: str) -> Path:
    """Write `out/<name>.md` (a header, then `body`, Markdown) and `out/<name>.json`
    (`figures`, with the header's facts), refresh the directory's index; returns the report's
    path. Directories are made as needed."""
    out.mkdir(parents=True, exist_ok=True)
    measured = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    host = host_facts()
    command = command_line()
    header = [
        f"# {title}",
        "",
        f"- command: `{command}`",
        f"- measured: {measured}, extensometer {__version__}",
        f"- host: {host['cores']} cores, {host['cpu']}, Python {host['python']}, {host['system']}",
        f"- figures: [{name}.json]({name}.json)",
        "",
    ]
    report = out / f"{name}.md"
    report.write_text("\n".join(header) + "\n" + body.rstrip() + "\n", encoding="utf-8")
    document = {
        "benchmark": name,
        "command": command,
        "measured_utc": measured,
        "software_version": __version__,
        "host": host,
        "figures": figures,
    }
    (out / f"{name}.json").write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    refresh_index(out)
    return report


def refresh_index(out: Path) -> None:
    """Write `out/README.md`: a table of every report in `out` (title, date, command)."""
    rows = []
    for report in sorted(out.glob("*.md")):
        if report.name == INDEX:
            continue
        facts: dict[str, str] = {}
        for line in report.read_text(encoding="utf-8").splitlines()[:8]:
            match = _HEADER.match(line)
            if match and match["title"] and "title" not in facts:
                facts["title"] = match["title"]
            elif match and match["key"]:
                facts[match["key"]] = match["value"]
        if "title" in facts:
            rows.append(
                f"| [{facts['title']}]({report.name}) | {facts.get('measured', '')} | "
                f"{facts.get('command', '')} |"
            )
    lines = [
        "# Benchmark results",
        "",
        "Written by the benchmarks themselves (`extensometer bench NAME --out DIR`); each report",
        "says what was run, when and on what host, and its figures are beside it as JSON.",
        "Refresh a report by running its benchmark again; do not edit these files by hand.",
        "",
        "| report | measured | command |",
        "|---|---|---|",
        *rows,
    ]
    (out / INDEX).write_text("\n".join(lines) + "\n", encoding="utf-8")


def emit_figures(
    name: str,
    title: str,
    figures: dict[str, Any],
    table: str,
    *,
    as_json: bool,
    out: Path | None,
) -> None:
    """Print `figures` (as JSON with `as_json`, else the human-readable `table`), and with
    `out` write them as the report `out/<name>.md` (the table) and `out/<name>.json`."""
    text = json.dumps(figures, indent=1)
    if out is not None:
        write_report(out, name, title, figures, f"```\n{table.rstrip()}\n```")
    sys.stdout.write(text + "\n" if as_json else table + "\n")
