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
import typer.core
import typer.main

try:  # typer >= 0.2x vendors click; its exceptions live there
    from typer import _click as _click
    from typer._click import exceptions as _click_exc
except ImportError:  # pragma: no cover - older typer uses click itself
    import click as _click
    from click import exceptions as _click_exc

from pihim.errors import PihimInputError

HELP = "Polarimetric drone inspection of heliostat fields."

#: The subcommands: name -> (module under ``pihim.cli``, function, the one-line help ``pihim --help`` shows).
#: A command's module (and what it imports: numpy, numba, scipy, pandas, ...) is imported only when that
#: command runs or shows its own help, so ``pihim --help`` and every command start quickly. The one-line
#: help is the first paragraph of the function's docstring (a test keeps the two equal).
COMMANDS: dict[str, tuple[str, str, str]] = {
    "polar": ("polar", "polar",
              "Turn raw mosaic frames into S0, DoLP and AoP images (float32 TIFF, AoP in degrees)."),
    "calibrate-polarizer": ("calibrate", "calibrate_polarizer",
                            "Estimate the analyser matrix from frames behind a linear polarizer rotated to known "
                            "angles."),
    "calibrate-camera": ("calibrate_camera", "calibrate_camera",
                         "Calibrate the camera (fx, fy, cx, cy, k1 k2 p1 p2 k3) from chessboard images with OpenCV."),
    "sky": ("sky", "sky", "All-sky DoLP and AoP maps (PNG polar plots and float arrays in .npz)."),
    "ground": ("ground", "ground",
               "Ground and mirror-reflected-ground AoP/DoLP maps over camera directions (paper Fig. 5c-d)."),
    "plan": ("plan", "plan", "Plan UFACET scan passes scored for polarimetric contrast and export missions."),
    "windows": ("windows", "windows",
                "Favourable times of day for polarimetric inspection (paper sec. 4.1 windows)."),
    "demo": ("demo", "demo", "Plan, render, inspect and score a polarimetric inspection; write DIR/report.html."),
    "simulate": ("simulate", "simulate",
                 "Render a raw polarimetric frame of the tracking field with its log and ground truth."),
    "edges": ("edges", "edges",
              "Edge maps of the S0, DoLP and AoP images of a raw frame (PNG edges, float32 TIFF gradients, JSON "
              "summary)."),
    "canting": ("canting", "canting",
                "Facet canting deviations of a heliostat from the target's reflection (canting.json + canting.png)."),
    "live": ("live", "live", "Live view in the browser: S0 / DoLP / AoP at 15 fps, adaptive exposure, raw capture."),
    "simulate-flight": ("campaign", "simulate_flight",
                        "Render the frames a flight of a plan would record, with its log and the truth beside it."),
    # a group of subcommands (a typer.Typer, not a function): its help is the group's
    "campaign": ("campaign", "app", "Campaigns at field scale: run, report, export."),
}

#: Commands registered eagerly with ``app.command(...)`` (plugins, tests) run as registered; the built-in
#: ones of :data:`COMMANDS` are registered lazily by :func:`command_group`.
app = typer.Typer(
    name="pihim",
    help=HELP,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def load_command(name: str) -> Any:
    """The function (or, for a group of subcommands, the ``typer.Typer``) behind the built-in command ``name``.

    Imports the command's module.
    """
    import importlib

    module, func, _ = COMMANDS[name]
    return getattr(importlib.import_module(f"pihim.cli.{module}"), func)


class LazyCommand(typer.core.TyperCommand):
    """A subcommand that imports its module only when it is run or shows its own help.

    ``pihim --help`` lists it from its name and one-line help alone; parsing
    its options, its help page and running it go through the real typer
    command, built on first use.
    """

    def __init__(self, name: str, short_help: str) -> None:
        super().__init__(name=name, help=short_help, short_help=short_help, add_help_option=False,
                         rich_markup_mode=app.rich_markup_mode)
        self._real: _click.Command | None = None

    def real(self) -> _click.Command:
        """The typer command of the function, or the group of a ``typer.Typer`` (built once)."""
        if self._real is None:
            target = load_command(str(self.name))
            if isinstance(target, typer.Typer):
                self._real = typer.main.get_command(target)
            else:
                single = typer.Typer(add_completion=False, pretty_exceptions_enable=False,
                                     rich_markup_mode=app.rich_markup_mode)
                single.command(self.name)(target)
                self._real = typer.main.get_command(single)
        return self._real

    def make_context(self, info_name: str | None, args: list[str], parent: Any = None, **extra: Any) -> Any:
        return self.real().make_context(info_name, args, parent=parent, **extra)

    def get_params(self, ctx: Any) -> list[Any]:
        return self.real().get_params(ctx)

    def get_help(self, ctx: Any) -> str:
        return self.real().get_help(ctx)

    def get_usage(self, ctx: Any) -> str:
        return self.real().get_usage(ctx)

    def invoke(self, ctx: Any) -> Any:
        return self.real().invoke(ctx)

    def shell_complete(self, ctx: Any, incomplete: str) -> list[Any]:
        return self.real().shell_complete(ctx, incomplete)


def command_group() -> typer.core.TyperGroup:
    """The ``pihim`` command group: the built-in commands (lazy) and any registered on :data:`app`."""
    commands: dict[str, _click.Command] = {name: LazyCommand(name, spec[2]) for name, spec in COMMANDS.items()}
    for info in app.registered_commands:
        cmd = typer.main.get_command_from_info(info, pretty_exceptions_short=app.pretty_exceptions_short,
                                               rich_markup_mode=app.rich_markup_mode)
        commands[str(info.name or cmd.name)] = cmd
    for group in app.registered_groups:
        sub = typer.main.get_command(group.typer_instance)
        commands[str(group.name or sub.name)] = sub
    return _Group(name="pihim", commands=commands, help=HELP, no_args_is_help=True,
                  rich_markup_mode=app.rich_markup_mode)


class _Group(typer.core.TyperGroup):
    """The ``pihim`` group: Ctrl-C in a command ends as :class:`typer.Abort`, which :func:`main` reports.

    (typer turns a KeyboardInterrupt into exit status 130 without a word.)
    """

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:
            raise typer.Abort() from exc


_COMMAND: dict[int, Any] = {}


def _command() -> Any:
    """:func:`command_group`, built once per set of commands registered on :data:`app`.

    (In-process callers, the tests above all, run many commands; the lazy
    commands keep their real typer command once built.)
    """
    key = len(app.registered_commands) + 1000 * len(app.registered_groups)
    if key not in _COMMAND:
        _COMMAND.clear()
        _COMMAND[key] = command_group()
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


def _wrapped_interrupt(exc: BaseException) -> BaseException | None:
    """The Ctrl-C or SIGTERM behind ``exc``, if any.

    An interrupt that arrives while compiled (numba) code calls back into Python reaches the caller as a
    ``SystemError`` whose cause or context is the interrupt.
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, (KeyboardInterrupt, Terminated)):
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return None


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


#: Options that take a path: typer turns an empty value into ``Path(".")``, so an empty one is refused up front.
_PATH_OPTIONS = frozenset({"--out", "-o", "--meta", "--facets", "--store", "--record", "--captures", "--cti", "--plan",
                           "--calibration"})


def _empty_path_option(args: list[str]) -> str | None:
    """The first path option given an empty value (``--out ''`` or ``--out=``), if any."""
    for k, arg in enumerate(args):
        if arg == "--":
            return None
        name, eq, value = arg.partition("=")
        if name in _PATH_OPTIONS and ((eq and not value) or (not eq and k + 1 < len(args) and args[k + 1] == "")):
            return name
    return None


def _empty_argument(args: list[str]) -> str | None:
    """The name of the first positional argument given an empty string (``pihim polar ''``), if any.

    typer turns it into ``Path(".")``, which would then be reported as the working directory. The command's own
    parameters tell which tokens are option values; an unknown command or option is left to the parser.
    """
    if "" not in args:
        return None
    cmd: Any = _command()
    k = 0
    while isinstance(cmd, typer.core.TyperGroup):  # down to the (sub)command, past the group's own flags
        while k < len(args) and args[k].startswith("-") and args[k] != "--":
            k += 1
        if k >= len(args) or cmd.get_command(None, args[k]) is None:  # type: ignore[arg-type]
            return None
        cmd = cmd.get_command(None, args[k])  # type: ignore[arg-type]
        cmd = cmd.real() if isinstance(cmd, LazyCommand) else cmd
        k += 1
    params = cmd.params
    options = [p for p in params if p.param_type_name == "option"]
    known = {name for p in options for name in p.opts + p.secondary_opts} | {"--help"}
    takes_value = {name for p in options if not p.is_flag and not p.count for name in p.opts + p.secondary_opts}
    # the positional slots in order, one per token (an argument of nargs=-1 takes every token that is left)
    slots = [p for p in params if p.param_type_name == "argument" for _ in range(max(p.nargs, 1))]
    open_ended = next((p for p in params if p.param_type_name == "argument" and p.nargs == -1), None)
    only_positional = False
    n_positional = 0
    while k < len(args):
        arg = args[k]
        if not only_positional and arg == "--":
            only_positional = True
        elif not only_positional and arg.startswith("-") and arg != "-":
            name = arg.partition("=")[0]
            if name not in known or name == "--help":  # an unknown option or the help: the parser's to report
                return None
            k += "=" not in arg and arg in takes_value  # the option's value is the next token
        else:
            slot = slots[n_positional] if n_positional < len(slots) else open_ended
            if slot is None:  # an extra argument: the parser's to report
                return None
            if arg == "":
                return slot.metavar or slot.name.upper()
            n_positional += 1
        k += 1
    return None


def _run(argv: list[str] | None) -> int:
    """The command, with every failure turned into one stderr line and an exit status."""
    args = sys.argv[1:] if argv is None else list(argv)
    empty = _empty_path_option(args)
    if empty is not None:
        print(f"pihim: error: {empty} needs a path, got an empty string", file=sys.stderr)
        return 2
    try:
        empty = _empty_argument(args)
        if empty is not None:
            raise PihimInputError(f"{empty} needs a path, got an empty string")
        rv = _command().main(args=argv, standalone_mode=False, prog_name="pihim")
    except PihimInputError as exc:
        print(f"pihim: error: {exc}", file=sys.stderr)
        return 2
    except _click_exc.NoArgsIsHelpError as exc:  # the help went to stdout: say on stderr what was missing
        print(f"pihim: error: {' '.join(exc.format_message().split()) or 'no command given (listed above)'}",
              file=sys.stderr)
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
        stop = _wrapped_interrupt(exc)
        if isinstance(stop, Terminated):
            raise stop from None  # main says "pihim: terminated", exit status 143
        if stop is not None:
            print("pihim: aborted", file=sys.stderr)
            return 130
        if os.environ.get("PIHIM_TRACEBACK"):
            raise
        print(f"pihim: error: internal error ({_one_line(exc)}); set PIHIM_TRACEBACK=1 for details",
              file=sys.stderr)
        return 1
    return int(rv or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
