"""Shared pieces of the command-line layer: option parsing and output helpers."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from pihim.camera.layout import MosaicLayout
from pihim.errors import PihimInputError

T = TypeVar("T")

#: Console for human-oriented output; stdout is kept for JSON.
stderr_console = Console(stderr=True)


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
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=stderr_console, transient=False) as bar:
        task = bar.add_task(description, total=len(items))
        for item in items:
            yield item
            bar.advance(task)


def report_error(message: str) -> None:
    """Print one error line on stderr."""
    print(f"pihim: error: {message}", file=sys.stderr)


def unique_stems(paths: Iterable[Any]) -> None:
    """Refuse batches in which two inputs would write the same output names."""
    seen: dict[str, Any] = {}
    for p in paths:
        if p.stem in seen:
            raise PihimInputError(f"{p} and {seen[p.stem]} share the name {p.stem!r}; outputs would collide")
        seen[p.stem] = p
