"""Shared pieces of the command-line layer: option parsing and output helpers."""

from __future__ import annotations

import functools
import json
import math
import sys
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from pihim._atomic import check_not_an_input, check_out_dir, make_out_dir, output_dir, output_target  # noqa: F401 - the commands import them from here
from pihim._inputs import check_regular_file
from pihim.camera.layout import MosaicLayout
from pihim.errors import PihimInputError

T = TypeVar("T")

if TYPE_CHECKING:
    from pathlib import Path

    from rich.console import Console

    from pihim.field import Field


@functools.cache
def stderr_console() -> Console:
    """The console for human-oriented output, on stderr (stdout is kept for JSON); made on first use.

    Importing rich takes 15-20 ms of CPU, which a command that writes JSON
    alone (``pihim polar FRAME --json``) never needs.
    """
    from rich.console import Console

    return Console(stderr=True)


def parse_layout(text: str) -> MosaicLayout:
    """``--layout`` value to a :class:`MosaicLayout` (errors are PihimInputError)."""
    return MosaicLayout.parse(text)


def parse_floats(text: str, *, name: str, count: int | None = None) -> list[float]:
    """Parse a comma-separated list of numbers for option ``name``."""
    try:
        vals = [float(p) for p in text.replace(";", ",").split(",") if p.strip()]
    except ValueError:
        raise PihimInputError(f"{name}: expected comma-separated numbers, got {text!r}") from None
    if count is not None and len(vals) != count:
        raise PihimInputError(f"{name}: expected {count} numbers, got {len(vals)}")
    return vals


def emit_json(obj: Any) -> None:
    """Print one JSON object on a single line to stdout (JSON Lines)."""
    sys.stdout.write(json.dumps(obj, allow_nan=False) + "\n")
    sys.stdout.flush()


def progress(items: Sequence[T], description: str, *, min_items: int = 2) -> Iterator[T]:
    """Iterate ``items`` with a progress bar on stderr when there are several."""
    if len(items) < min_items:
        yield from items
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    )
    # only on a terminal: piped into a log, a bar is one more line that says nothing
    with Progress(*columns, console=stderr_console(), transient=False,
                  disable=not stderr_console().is_terminal) as bar:
        task = bar.add_task(description, total=len(items))
        for item in items:
            yield item
            bar.advance(task)


def report_error(message: str) -> None:
    """Print one error line on stderr."""
    print(f"pihim: error: {message}", file=sys.stderr)


def field_csv_option(spec: str, facets: "Path | None") -> "Path | None":
    """``--field nsttf-like|HELIOSTATS.csv`` (and ``--facets``): None for the embedded field, else the CSV file.

    Both files are checked (one-line :class:`PihimInputError`); nothing is read.
    """
    from pathlib import Path

    key = spec.strip()
    if key.lower() in ("nsttf-like", "nsttf"):
        if facets is not None:
            raise PihimInputError("--facets needs --field HELIOSTATS.csv (the nsttf-like field has its own facets)")
        return None
    if not key:
        raise PihimInputError("--field is empty: give nsttf-like or a heliostat CSV file")
    path = Path(key)
    if not path.exists():
        raise PihimInputError(f"--field {spec!r}: neither 'nsttf-like' nor an existing heliostat CSV file")
    check_regular_file(path, "heliostat CSV file", option="--field")
    if facets is not None:
        check_regular_file(facets, "facet CSV file", option="--facets")
    return path


def load_field_option(spec: str, facets: "Path | None", *, nsttf_tower: bool = True) -> "Field":
    """``--field nsttf-like|HELIOSTATS.csv`` (and ``--facets``) to a :class:`pihim.field.Field`."""
    from pihim.field import NSTTF_TOWER, load_field, nsttf_like_field

    path = field_csv_option(spec, facets)
    if path is None:
        return nsttf_like_field()
    return load_field(path, facets, tower=NSTTF_TOWER if nsttf_tower else None)


#: Largest field-frame coordinate a point option accepts, metres: 100 km from the field's origin, far beyond any
#: heliostat field, so that a mistyped exponent is refused instead of overflowing the geometry.
MAX_POINT_COORDINATE_M = 1e5


def parse_point(text: str | None, *, name: str) -> "list[float] | None":
    """``X,Y,Z`` in metres (finite, within :data:`MAX_POINT_COORDINATE_M` of the origin) or None."""
    if text is None:
        return None
    vals = parse_floats(text, name=name, count=3)
    if not all(math.isfinite(v) for v in vals):
        raise PihimInputError(f"{name}: coordinates must be finite")
    if max(abs(v) for v in vals) > MAX_POINT_COORDINATE_M:
        raise PihimInputError(f"{name}: coordinates must be within {MAX_POINT_COORDINATE_M:g} m of the field origin, "
                              f"got {text}")
    return vals
