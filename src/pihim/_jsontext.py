"""Indented JSON text that stays fast for large documents (private).

:func:`json.dumps` with ``indent`` runs Python's pure-Python encoder (the C
encoder serves only ``indent=None``), about 4x slower than compact output
and twice the size: a 100,000-heliostat ``plan.json`` spent most of a minute
there. :func:`json_text` lays out the outer levels of a document one member
per line, as ``indent`` does, and writes each value below ``inline_depth`` on
one line with the C encoder -- e.g. one waypoint per line.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

__all__ = ["json_text", "write_json_text"]


def _key(k: Any) -> str:
    """A dictionary key as :func:`json.dumps` writes it (str, int, finite float, bool or None)."""
    if isinstance(k, str):
        return k
    if k is True or k is False or k is None:
        return {True: "true", False: "false", None: "null"}[k]
    if isinstance(k, int):
        return int.__repr__(k)
    if isinstance(k, float):
        if k != k or k in (float("inf"), float("-inf")):
            raise ValueError(f"out of range float key for JSON: {k!r}")
        return float.__repr__(k)
    raise TypeError(f"keys must be str, int, float, bool or None, not {type(k).__name__}")


def json_text(obj: Any, *, indent: int = 2, inline_depth: int | None = None, sort_keys: bool = False) -> str:
    """JSON text of ``obj``, indented down to ``inline_depth``, each deeper value on one line.

    Parameters
    ----------
    obj : dict, list or JSON scalar
        Document of dicts, lists/tuples, str, int, float (finite), bool, None.
    indent : int
        Spaces per level.
    inline_depth : int, optional
        Containers nested this deep (the document itself is depth 0) are
        written on one line, with ``", "`` and ``": "`` separators. None:
        no limit, the text equals ``json.dumps(obj, indent=indent,
        sort_keys=sort_keys)`` (tested).
    sort_keys : bool
        Sort dictionary keys, at every depth (as their JSON strings; the
        same order as :func:`json.dumps` gives for str keys).

    Returns
    -------
    str
        Without a trailing newline.

    Raises
    ------
    ValueError
        A non-finite float (JSON has none), as ``json.dumps(allow_nan=False)``.
    TypeError
        A value JSON cannot hold.
    """
    chunks: list[str] = []
    write_json_text(obj, chunks.append, indent=indent, inline_depth=inline_depth, sort_keys=sort_keys)
    return "".join(chunks)


def write_json_text(obj: Any, write: Callable[[str], Any], *, indent: int = 2, inline_depth: int | None = None,
                    sort_keys: bool = False, chunk_parts: int = 1 << 16) -> None:
    """:func:`json_text` of ``obj`` passed to ``write`` in consecutive pieces (e.g. a text file's ``write``).

    A piece joins ``chunk_parts`` strings of the text (a megabyte or two for a plan), so a document's text
    never lies in memory whole, nor as millions of small strings. On an error, the pieces written so far
    are the start of the text.
    """
    leaf = json.JSONEncoder(allow_nan=False, sort_keys=sort_keys, separators=(", ", ": ")).encode
    limit = float("inf") if inline_depth is None else inline_depth
    parts: list[str] = []
    add = parts.append

    def flush() -> None:
        write("".join(parts))
        parts.clear()

    def walk(o: Any, depth: int) -> None:
        if depth >= limit or not isinstance(o, (dict, list, tuple)) or not o:
            add(leaf(o))
            return
        pad = "\n" + " " * (indent * (depth + 1))
        if isinstance(o, dict):
            items = [(_key(k), v) for k, v in o.items()]
            if sort_keys:
                items.sort(key=lambda kv: kv[0])
            add("{")
            for n, (k, v) in enumerate(items):
                add(pad if n == 0 else "," + pad)
                add(leaf(k))
                add(": ")
                walk(v, depth + 1)
                if len(parts) >= chunk_parts:
                    flush()
            add("\n" + " " * (indent * depth) + "}")
        else:
            add("[")
            for n, v in enumerate(o):
                add(pad if n == 0 else "," + pad)
                walk(v, depth + 1)
                if len(parts) >= chunk_parts:
                    flush()
            add("\n" + " " * (indent * depth) + "]")

    walk(obj, 0)
    flush()
