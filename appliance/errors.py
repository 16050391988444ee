"""Errors the appliance reports to its user as one line, naming the culprit."""

from pathlib import Path


class InputError(Exception):
    """Bad input from the user: a file, a line of a file, a key or a value.

    The message is one line and names the culprit (path, line number, key or register);
    the command line prints it and exits with status 2.
    """


class ParameterError(ValueError):
    """A value a domain function refuses for one of its parameters.

    Attributes:
        parameter: the parameter's name (`object_distance_mm`), so a caller can name its own
            spelling of it (a command-line option, a configuration key).
        reason: why, one line; the message is `parameter reason`.
    """

    def __init__(self, parameter: str, reason: str) -> None:
        super().__init__(f"{parameter} {reason}")
        self.parameter = parameter
        self.reason = reason


def read_user_text(path: Path, what: str) -> str:
    """Read a UTF-8 text file the user named; `what` names it in the one-line error.

    Raises:
        InputError: "<path>: no such <what>" or "<path>: cannot read <what> (<reason>)".
    """
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read {what} ({exc})") from None
