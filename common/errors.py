"""Errors meant for a person: the CLI prints them as one line and exits with code 2."""


class UserError(Exception):
    """Bad input from the user (a file, a name, an option); the message names the problem."""

    exit_code = 2
