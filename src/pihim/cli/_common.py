"""Shared pieces of the command-line layer: option parsing and output helpers."""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from pihim.camera.layout import MosaicLayout
from pihim.errors import PihimInputError

T = TypeVar("T")

if TYPE_CHECKING:
    from pathlib import Path

    from pihim.field import Field

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
    # only on a terminal: piped into a log, a bar is one more line that says nothing
    with Progress(*columns, console=stderr_console, transient=False, disable=not stderr_console.is_terminal) as bar:
        task = bar.add_task(description, total=len(items))
        for item in items:
            yield item
            bar.advance(task)


def report_error(message: str) -> None:
    """Print one error line on stderr."""
    print(f"pihim: error: {message}", file=sys.stderr)


def check_out_dir(out: "Path", *, option: str = "--out") -> None:
    """Refuse an output directory that cannot be one, before any work is done.

    ``out`` must be a directory or not exist yet; its nearest existing
    ancestor must be a writable directory; and a missing ``out`` must be
    creatable: it is created and removed again at once (so that, say,
    ``--out /proc/x`` is refused before a long computation, not after it).
    Nothing is left behind (see :func:`make_out_dir`).
    """
    import contextlib
    import os
    from pathlib import Path

    p = Path(out)
    if p.exists() and not p.is_dir():
        raise PihimInputError(f"{option} {out}: exists and is not a directory")
    missing: list[Path] = []
    existing = None
    for q in (p.absolute(), *p.absolute().parents):
        if q.exists():
            if not q.is_dir():
                raise PihimInputError(f"{option} {out}: {q} is not a directory")
            existing = q
            break
        missing.append(q)
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise PihimInputError(f"{option} {out}: cannot write in {existing} (permission denied)")
    if not missing:
        return
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PihimInputError(f"{option} {out}: cannot create the directory ({exc.strerror or exc})") from None
    finally:
        for q in missing:  # deepest first; a folder another process filled meanwhile is not empty and stays
            with contextlib.suppress(OSError):
                q.rmdir()


def make_out_dir(out: "Path", *, option: str = "--out") -> "Path":
    """Create the output directory (one-line error if impossible) and clean stale temporaries in it.

    Temporary files that killed runs left behind (see
    :func:`pihim._atomic.clean_stale_temporaries`) are removed.
    """
    from pathlib import Path

    from pihim._atomic import clean_stale_temporaries

    p = Path(out)
    check_out_dir(p, option=option)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PihimInputError(f"{option} {out}: cannot create the directory ({exc.strerror or exc})") from None
    clean_stale_temporaries(p)
    return p


def load_field_option(spec: str, facets: "Path | None", *, nsttf_tower: bool = True) -> "Field":
    """``--field nsttf-like|HELIOSTATS.csv`` (and ``--facets``) to a :class:`pihim.field.Field`."""
    from pathlib import Path

    from pihim.field import NSTTF_TOWER, load_field, nsttf_like_field

    key = spec.strip()
    if key.lower() in ("nsttf-like", "nsttf"):
        if facets is not None:
            raise PihimInputError("--facets needs --field HELIOSTATS.csv (the nsttf-like field has its own facets)")
        return nsttf_like_field()
    path = Path(key)
    if not path.is_file():
        raise PihimInputError(f"--field {spec!r}: neither 'nsttf-like' nor an existing heliostat CSV file")
    if facets is not None and not Path(facets).is_file():
        raise PihimInputError(f"--facets {facets}: no such file")
    return load_field(path, facets, tower=NSTTF_TOWER if nsttf_tower else None)


def parse_point(text: str | None, *, name: str) -> "list[float] | None":
    """``X,Y,Z`` in metres (finite) or None."""
    if text is None:
        return None
    vals = parse_floats(text, name=name, count=3)
    if not all(math.isfinite(v) for v in vals):
        raise PihimInputError(f"{name}: coordinates must be finite")
    return vals
