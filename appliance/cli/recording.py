"""`extensometer replay` and `extensometer info`: recordings measured again, and summarised.

`replay` measures a recorded test again from its recorded pixels
(`appliance.recording.replay.replay_recording`), with the test's results in its summary
(`appliance.results`); with `--out DIR` it writes `report.html` and `summary.json` there (a
directory that cannot be made refuses the replay, exit status 2; a file that cannot be written
is said in one line, exit status 1). It exits 1 when the file is damaged (one line
on stderr: the damage, how many of the recorded samples were measured, and where the reference
frame was read when not from its attachment) or, without an override, when any sample differs
from the recording; `info` reads a recording front to back with every CRC checked
(`appliance.recording.info`) and exits 1 when the file is not whole. Both refuse a file that is
not one extensometer recording with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from appliance.cli import arguments
from appliance.cli.printing import print_json, print_summary
from appliance.cli.run import viewer_of
from appliance.errors import InputError

if TYPE_CHECKING:
    from appliance.results.report_output import TestReport
    from appliance.run.summary import RunOutcome


def add_parsers(commands: argparse._SubParsersAction) -> None:
    """The `replay` and `info` commands."""
    replay = commands.add_parser(
        "replay",
        help="measure a recorded test again from its recorded pixels",
        description=(
            "Re-run the tracker on the pixels recorded in FILE.mcap with the recorded "
            "configuration: the strain series is reproduced bit for bit "
            "(max_abs_diff_to_recorded = 0.0). With --config, the tables and keys of that "
            "file replace the recorded ones and the test is measured again. A damaged file "
            "is replayed up to the damage, which is reported (exit status 1)."
        ),
    )
    replay.add_argument("recording", metavar="FILE.mcap", type=Path, help="a recording")
    replay.add_argument(
        "--config", type=Path, metavar="OVERRIDE", help="TOML tables replacing recorded keys"
    )
    replay.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="output directory for report.html, summary.json",
    )
    arguments.add_rerun_options(replay)
    replay.add_argument("--json", action="store_true", help="print the summary as JSON, quietly")
    replay.set_defaults(handler=replay_test)

    info = commands.add_parser(
        "info",
        help="summarise a recording and check its integrity",
        description=(
            "Read FILE.mcap front to back, checking every CRC, and print what it holds: the "
            "test, its channels and message counts, how the run ended, and any damage."
        ),
    )
    info.add_argument("recording", metavar="FILE.mcap", type=Path, help="a recording")
    info.add_argument("--json", action="store_true", help="print JSON on stdout")
    info.set_defaults(handler=show_info)


def replay_test(args: argparse.Namespace) -> int:
    """Run `replay`; returns the exit status."""
    from appliance.recording.replay import is_exact, replay_recording
    from appliance.results.report_output import TestReport

    if args.out is not None:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"{args.out}: cannot create ({exc.strerror})") from None
    progress = None if args.json or not sys.stderr.isatty() else sys.stderr
    viewer = viewer_of(arguments.configuration(None, args))
    viewers = [viewer] if viewer is not None else []
    for output in viewers:
        output.start()
    report = TestReport()
    try:
        outcome = replay_recording(
            args.recording, override=args.config, outputs=[report, *viewers], progress=progress
        )
    finally:
        for output in viewers:
            output.close()
    unwritten = _write_outputs(args.out, report, outcome) if args.out is not None else None
    if args.json:
        print(outcome.to_json())
    else:
        print_summary(outcome)
    if unwritten is not None:
        print(f"extensometer: {unwritten}", file=sys.stderr)
        return 1
    if outcome.extra.get("damage"):
        print(f"extensometer: {args.recording}: {outcome.summary.reason}", file=sys.stderr)
        return 1
    if args.config is None and not is_exact(outcome):
        print(
            f"extensometer: {args.recording}: {outcome.extra['samples_differing']} samples "
            "differ from the recording",
            file=sys.stderr,
        )
        return 1
    return 0


def _write_outputs(out: Path, report: TestReport, outcome: RunOutcome) -> str | None:
    """Write `report.html` and `summary.json` into `out`; the first that could not be written,
    as one line, or None."""
    from appliance.results.report_output import REPORT_NAME

    page = out / REPORT_NAME
    report.write(page, outcome)
    failures = [] if outcome.extra["report"] == str(page) else [outcome.extra["report"]]
    summary = out / "summary.json"
    try:
        summary.write_text(outcome.to_json() + "\n")
    except OSError as exc:
        failures.append(f"{summary}: cannot write ({exc.strerror})")
    return failures[0] if failures else None


def show_info(args: argparse.Namespace) -> int:
    """Run `info`; exit status 1 when the recording is damaged."""
    from appliance.recording.info import print_info, recording_info

    info = recording_info(args.recording)
    if args.json:
        print_json(info, indent=1)
    else:
        print_info(info, sys.stdout)
    if info["damage"]:
        print(f"extensometer: {args.recording}: {info['damage']}", file=sys.stderr)
        return 1
    return 0
