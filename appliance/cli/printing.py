"""How commands show results on stdout: aligned `key value` lines, or JSON."""

from __future__ import annotations

import json
import sys
from typing import Any, TextIO

from appliance.run.summary import RunOutcome


def print_summary(outcome: RunOutcome, stream: TextIO = sys.stdout) -> None:
    """A run's or a replay's summary as aligned human-readable lines; a fact the run does not
    have (null in summary.json) shows as `-`."""
    for key, value in outcome.as_dict().items():
        if value is None:
            value = "-"
        elif isinstance(value, float):
            value = f"{value:.6g}"
        stream.write(f"{key:38s} {value}\n")


def print_json(document: Any, stream: TextIO = sys.stdout, *, indent: int = 2) -> None:
    """A JSON document and a newline."""
    json.dump(document, stream, indent=indent)
    stream.write("\n")
