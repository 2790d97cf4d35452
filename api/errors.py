"""Exceptions the command line and the service turn into clear one-line messages.

``InputError`` subclasses ValueError so code that already catches ValueError (core raises
ValueError for bad arguments) keeps working; the CLI maps both to exit status 2.
"""
from __future__ import annotations


class GravcalError(Exception):
    """Base class of gravcal's own errors (message meant for the user, no traceback)."""


class InputError(GravcalError, ValueError):
    """The user's input (a file, an option) is unusable; the message names the problem."""


class NotTrustworthy(GravcalError):
    """A calibration was computed but must not be used (not converged / not observable)."""
