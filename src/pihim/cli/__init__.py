"""The ``pihim`` command line: a thin layer over the Python API.

Every command reports invalid input as one line on stderr and exits with
status 2; computed results can be printed as JSON (``--json``).
"""

from __future__ import annotations

import logging
import sys
import warnings

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


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Show library warnings as one ``pihim: warning:`` line, without source context."""
    print(f"pihim: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 1 some items failed, 2 bad input)."""
    # readers turn corrupt files into one-line errors; silence tifffile's own log lines
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    warnings.showwarning = _one_line_warning
    try:
        rv = app(args=argv, standalone_mode=False, prog_name="pihim")
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
    return int(rv or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
