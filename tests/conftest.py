"""Settings for the whole suite."""

import signal

_SIGINT_BEFORE = []


def pytest_configure(config):
    """Give the suite Python's own Ctrl-C handler when it was started with SIGINT ignored.

    A non-interactive shell starts a background job (``pytest &``) with SIGINT ignored, and the processes it
    starts inherit that; the tests that send SIGINT to a command (its clean stop, exit 130) need the handler a
    foreground run has. A handled signal is reset to the default in a started process, so they get it too.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        _SIGINT_BEFORE.append(signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_unconfigure(config):
    """Put back what :func:`pytest_configure` changed."""
    while _SIGINT_BEFORE:
        signal.signal(signal.SIGINT, _SIGINT_BEFORE.pop())
