"""The ``pihim`` command line: a thin layer over the Python API.

Every command reports invalid input as one line on stderr and exits with
status 2; computed results can be printed as JSON (``--json``). Exit
statuses: 0 success; 2 bad input (an option, a file, or a request larger
than the memory of the machine), also when only some items of a batch were
bad; 1 an operating-system error while writing, or an internal error; 130
interrupted (SIGINT), 143 terminated (SIGTERM). No status comes with a
traceback unless ``PIHIM_TRACEBACK=1`` is set.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import typer

try:  # typer >= 0.2x vendors click; its exceptions live there
    from typer._click import exceptions as _click_exc
except ImportError:  # pragma: no cover - older typer uses click itself
    from click import exceptions as _click_exc

from pihim.cli import calibrate, calibrate_camera, canting, demo, edges, ground, plan, polar, simulate, sky, windows
from pihim.errors import PihimInputError

app = typer.Typer(
    name="pihim",
    help="Polarimetric drone inspection of heliostat fields.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.command("polar")(polar.polar)
app.command("calibrate-polarizer")(calibrate.calibrate_polarizer)
app.command("calibrate-camera")(calibrate_camera.calibrate_camera)
app.command("sky")(sky.sky)
app.command("ground")(ground.ground)
app.command("plan")(plan.plan)
app.command("windows")(windows.windows)
app.command("demo")(demo.demo)
app.command("simulate")(simulate.simulate)
app.command("edges")(edges.edges)
app.command("canting")(canting.canting)


_COMMAND: dict[int, Any] = {}


def _command() -> Any:
    """The click command behind ``app``, built once (building it costs more than many a command's run)."""
    key = len(app.registered_commands)
    if key not in _COMMAND:
        _COMMAND.clear()
        _COMMAND[key] = typer.main.get_command(app)
    return _COMMAND[key]


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Show library warnings as one ``pihim: warning:`` line, without source context."""
    print(f"pihim: warning: {message}", file=sys.stderr)


class Terminated(BaseException):
    """Raised in the main thread on SIGTERM, so that temporary files are removed as on Ctrl-C."""


def _raise_terminated(signum: int, frame: object) -> None:  # noqa: ARG001
    raise Terminated(signum)


@contextmanager
def _sigterm_raises() -> Iterator[None]:
    """Turn SIGTERM into :class:`Terminated` for the duration of the block (main thread only)."""
    try:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    except (ValueError, OSError):  # not the main thread, or no signals here
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _one_line(exc: BaseException) -> str:
    """An exception as one line of text."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 bad input, 1 write or internal error, 130/143 stopped)."""
    # readers turn corrupt files into one-line errors; silence tifffile's own log lines
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    warnings.showwarning = _one_line_warning
    with _sigterm_raises():
        try:
            return _run(argv)
        except Terminated:
            print("pihim: terminated", file=sys.stderr)
            return 128 + signal.SIGTERM


def _run(argv: list[str] | None) -> int:
    """The command, with every failure turned into one stderr line and an exit status."""
    try:
        rv = _command()(args=argv, standalone_mode=False, prog_name="pihim")
    except PihimInputError as exc:
        print(f"pihim: error: {exc}", file=sys.stderr)
        return 2
    except _click_exc.NoArgsIsHelpError as exc:
        print(exc.format_message(), file=sys.stderr)
        return 2
    except _click_exc.UsageError as exc:
        print(f"pihim: error: {' '.join(exc.format_message().split())}", file=sys.stderr)
        return 2
    except typer.Exit as exc:
        return int(exc.exit_code)
    except typer.Abort:
        print("pihim: aborted", file=sys.stderr)
        return 130
    except MemoryError:
        from pihim._resources import memory_error_message

        print(f"pihim: error: {memory_error_message('this request')}", file=sys.stderr)
        return 2
    except RecursionError:
        print("pihim: error: input nested too deeply", file=sys.stderr)
        return 2
    except OSError as exc:
        from pihim._atomic import describe_os_error

        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"pihim: error: {where}{describe_os_error(exc)}", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - the promise is one line, never a traceback
        if os.environ.get("PIHIM_TRACEBACK"):
            raise
        print(f"pihim: error: internal error ({_one_line(exc)}); set PIHIM_TRACEBACK=1 for details",
              file=sys.stderr)
        return 1
    return int(rv or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
