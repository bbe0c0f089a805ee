"""Settings for the whole suite."""

import signal


def pytest_configure(config):
    """Give the suite Python's own Ctrl-C handler when it was started with SIGINT ignored.

    A shell starts a background job (``pytest &``, ``nohup``) with SIGINT ignored, and the processes it starts
    inherit that; the tests that send SIGINT to a command (its clean stop, exit 130) need the handler a
    foreground run has. A handled signal is reset to the default in a started process, so they get it too.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
