"""How a benchmark hands over its figures: JSON to a file, and JSON or a table on stdout."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any


def emit_figures(figures: dict[str, Any], table: str, *, as_json: bool, out: Path | None) -> None:
    """Write `figures` as JSON to `out` (directories made) when given, and print them: as JSON
    with `as_json`, else as the human-readable `table`."""
    text = json.dumps(figures, indent=1)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n", encoding="utf-8")
    sys.stdout.write(text + "\n" if as_json else table + "\n")
