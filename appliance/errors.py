"""Errors the appliance reports to its user as one line, naming the culprit."""


class InputError(Exception):
    """Bad input from the user: a file, a line of a file, a key or a value.

    The message is one line and names the culprit (path, line number, key or register);
    the command line prints it and exits with status 2.
    """
