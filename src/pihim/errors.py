"""Exception types raised by pihim for invalid user input."""

from __future__ import annotations


class PihimInputError(ValueError):
    """Invalid input supplied by a user (file, parameter or array).

    The message is a single line meant to be shown as is; the command-line
    interface prints it on stderr and exits with status 2.
    """
