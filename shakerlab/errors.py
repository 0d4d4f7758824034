"""Errors shared across packages."""


class UserFacingError(Exception):
    """Bad input from the user (file, option, config field).

    The command line prints the message without a traceback, so the message
    must name the problem precisely: the file, the field or line, and what was
    expected.
    """


class EstimateRefused(UserFacingError):
    """The recording does not determine part of an estimate (not an input error): reconstruct
    records it and goes on to its other passes and, failing them, to the simpler models."""


class Terminated(KeyboardInterrupt):
    """SIGTERM: handled like Ctrl-C (everything being written is discarded, existing files stay as they
    were); the command line exits with 143 (128 + SIGTERM) instead of 130."""
