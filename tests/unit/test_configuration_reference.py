"""The configuration reference (appliance/CONFIGURATION.md) names every key of every table."""

import dataclasses
import re
from pathlib import Path

from appliance.config import Config

REFERENCE = Path(__file__).resolve().parents[2] / "appliance" / "CONFIGURATION.md"


def _section(text: str, table: str) -> str:
    match = re.search(rf"^## `\[{table}\]`.*?(?=^## |\Z)", text, flags=re.MULTILINE | re.DOTALL)
    assert match, f"{REFERENCE}: no section for [{table}]"
    return match.group(0)


def test_every_table_and_key_is_in_the_reference():
    text = REFERENCE.read_text(encoding="utf-8")
    missing = []
    for table in dataclasses.fields(Config):
        section = _section(text, table.name)
        for key in dataclasses.fields(table.default_factory()):
            if key.metadata.get("configurable", True) and f"`{key.name}`" not in section:
                missing.append(f"[{table.name}] {key.name}")
    assert not missing, f"{REFERENCE} does not describe: {', '.join(missing)}"
