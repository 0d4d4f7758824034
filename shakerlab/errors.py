"""Errors shared across packages."""


class UserFacingError(Exception):
    """Bad input from the user (file, option, config field).

    The command line prints the message without a traceback, so the message
    must name the problem precisely: the file, the field or line, and what was
    expected.
    """
