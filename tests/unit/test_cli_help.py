"""Every command and sub-command of `extensometer` prints its help and exits 0."""

from __future__ import annotations

import argparse

import pytest

from appliance.cli import build_parser, main


def _command_lines(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> list:
    lines = [prefix]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                lines += _command_lines(child, (*prefix, name))
    return lines


COMMAND_LINES = _command_lines(build_parser())


def test_every_command_is_found() -> None:
    names = {line[0] for line in COMMAND_LINES if line}
    assert {"run", "serve", "track", "bench", "calibrate", "verify"} <= names


@pytest.mark.parametrize("command", COMMAND_LINES, ids=lambda line: " ".join(line) or "-")
def test_help(command: tuple[str, ...], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as end:
        main([*command, "--help"])
    assert end.value.code == 0
    assert "usage: extensometer" in capsys.readouterr().out
