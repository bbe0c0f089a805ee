"""Reading input files safely: regular files only, bounded sizes, no recursion overflow on JSON.

A FIFO or a character device given as an input (``mkfifo x.raw``) would block
a reader forever or feed it without end; a JSON document nested 100,000 deep
exhausts Python's recursion limit. The helpers here refuse both with one-line
:class:`~pihim.errors.PihimInputError` messages that start with the path.
"""

from __future__ import annotations

import json
import math
import os
import stat
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pihim.errors import PihimInputError

#: Largest text input (JSON metadata, calibration, CSV) read, bytes.
MAX_TEXT_BYTES = 256 << 20


def check_regular_file(path: str | os.PathLike[str], what: str = "file", *,
                       option: str | None = None) -> os.stat_result:
    """``os.stat`` of ``path``, refusing anything but an existing regular file (symlinks followed).

    Raises
    ------
    PihimInputError
        ``"<path>: no such file"``, ``"<path>: is a directory, not a <what>"``,
        ``"<path>: not a regular file (a FIFO, device or socket); give a <what>"``;
        with ``option`` (e.g. ``"--plan"``) the message starts ``"<option> <path>: "``.
    """
    label = os.fspath(path) if option is None else f"{option} {os.fspath(path)}"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise PihimInputError(f"{label}: no such file") from None
    except OSError as exc:
        raise PihimInputError(f"{label}: cannot read file: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise PihimInputError(f"{label}: is a directory, not a {what}")
    if not stat.S_ISREG(st.st_mode):
        raise PihimInputError(f"{label}: not a regular file (a FIFO, device or socket); give a {what}")
    return st


def check_distinct(paths: Sequence[str | os.PathLike[str]], what: str = "file") -> None:
    """Refuse an input file given twice (another spelling or a link to it included).

    For inputs that count as independent measurements (calibration views,
    frames combined into one estimate): the same file twice would be counted
    twice. Compared by device and inode; paths that cannot be looked at are
    left to the reader's own error.

    Raises
    ------
    PihimInputError
        ``"<path>: given twice; give each <what> once"`` (or ``"<path> and
        <path>: the same file; ..."`` for two spellings of one file).
    """
    seen: dict[tuple[int, int], str] = {}
    for p in paths:
        try:
            st = os.stat(p)
        except (OSError, ValueError):
            continue
        key = (st.st_dev, st.st_ino)
        if key in seen:
            first, again = seen[key], os.fspath(p)
            where = f"{again}: given twice" if first == again else f"{first} and {again}: the same file"
            raise PihimInputError(f"{where}; give each {what} once")
        seen[key] = os.fspath(p)


def read_text_file(path: str | os.PathLike[str], what: str = "file", *, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text (BOM tolerated) of a regular file of at most ``max_bytes``."""
    label = os.fspath(path)
    st = check_regular_file(path, what)
    if st.st_size > max_bytes:
        raise PihimInputError(f"{label}: {st.st_size} bytes is too large for a {what} (at most {max_bytes})")
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise PihimInputError(f"{label}: cannot read file: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise PihimInputError(f"{label}:{line}: {what} is not UTF-8 text ({exc.reason})") from None


def loads_json(text: str, label: str, what: str = "JSON file") -> Any:
    """Parse JSON text; malformed or too deeply nested documents are one-line errors.

    Raises
    ------
    PihimInputError
        ``"<label>: not a readable <what>: not valid JSON (line L column C: reason)"``, or
        ``"<label>: <what> is nested too deeply"`` when the parser runs out of
        recursion depth (arrays within arrays some thousand levels deep).
    """
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise PihimInputError(
            f"{label}: not a readable {what}: not valid JSON (line {exc.lineno} column {exc.colno}: {exc.msg})"
        ) from None
    except RecursionError:
        raise PihimInputError(f"{label}: {what} is nested too deeply") from None
    except ValueError as exc:  # e.g. an integer beyond Python's digit limit
        raise PihimInputError(f"{label}: not a readable {what} ({' '.join(str(exc).split())})") from None


def load_json_file(path: str | os.PathLike[str], what: str = "JSON file") -> Any:
    """Read and parse a JSON file with :func:`read_text_file` and :func:`loads_json`."""
    return loads_json(read_text_file(path, what), os.fspath(path), what)


def finite_number(value: Any, what: str) -> float:
    """``value`` as a finite float, or a one-line :class:`PihimInputError` naming ``what``.

    Booleans are refused (``True`` is not a number of anything here).
    """
    if isinstance(value, bool):
        raise PihimInputError(f"{what} must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise PihimInputError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise PihimInputError(f"{what} must be finite, got {value!r}")
    return x
