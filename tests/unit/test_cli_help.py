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


def test_an_output_directory_that_is_a_file_is_refused_before_the_work_starts(tmp_path):
    from appliance.cli.arguments import output_directory

    afile = tmp_path / "afile"
    afile.write_text("")
    assert output_directory(str(tmp_path / "new" / "dir")) == tmp_path / "new" / "dir"
    assert output_directory(str(tmp_path)) == tmp_path
    for culprit in (afile, afile / "below"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"{afile} is not a directory"):
            output_directory(str(culprit))
