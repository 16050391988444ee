"""Recordings of older format versions, read as the current version.

Recordings are archives: a file written by an earlier release still opens, replays and
reports. The writer stores the format version in the `extensometer.recording` metadata
(`appliance.recording.format.FORMAT_VERSION`); the reader passes what it reads through the
functions here, which turn an older version's names into the current ones and leave the
current version's untouched. Nothing is written back: the file stays as it was recorded.

Version 1 called the testing machine the "frame": its recorded configuration has a table
named `frame` (with `url = "sim://frame"` in simulated tests), the machine's state is on
`/frame/state`, the run facts say `frame_url` and the devices `frame`. Version 2 says
`machine` for the table, `sim://machine`, `/machine/state`, `machine_url` and `machine`.
"""

from __future__ import annotations

from typing import Any

from appliance.recording.format import FORMAT_VERSION, TOPIC_MACHINE

CURRENT_VERSION = int(FORMAT_VERSION)

_V1_TOPIC_MACHINE = "/frame/state"


def machine_topic(version: int) -> str:
    """The topic the machine's state was recorded on in a format version."""
    return _V1_TOPIC_MACHINE if version == 1 else TOPIC_MACHINE


def config_table(table: dict[str, Any], version: int) -> dict[str, Any]:
    """A recorded configuration (as tables) in the current version's names."""
    if version != 1 or "frame" not in table:
        return table
    migrated = {("machine" if key == "frame" else key): value for key, value in table.items()}
    machine = dict(migrated["machine"])
    if machine.get("url") == "sim://frame":
        machine["url"] = "sim://machine"
    migrated["machine"] = machine
    return migrated


def run_facts(facts: dict[str, Any], version: int) -> dict[str, Any]:
    """Recorded run facts in the current version's names."""
    return _renamed(facts, "frame_url", "machine_url") if version == 1 else facts


def devices(recorded: dict[str, str], version: int) -> dict[str, str]:
    """Recorded device identities in the current version's names."""
    return _renamed(recorded, "frame", "machine") if version == 1 else recorded


def _renamed(table: dict[str, Any], old: str, new: str) -> dict[str, Any]:
    """`table` with key `old` called `new`, and a version 1 simulated machine's URL updated."""
    renamed = {(new if key == old else key): value for key, value in table.items()}
    if renamed.get(new) == "sim://frame":
        renamed[new] = "sim://machine"
    return renamed
