"""pihim._jsontext against the standard library's encoder (the oracle)."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim._jsontext import json_text, write_json_text

_scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12),
                     st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=8))
_keys = st.text(max_size=6)
documents = st.recursive(_scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                           st.dictionaries(_keys, inner, max_size=4)), max_leaves=30)


@settings(max_examples=300, deadline=None)
@given(documents, st.integers(0, 4), st.booleans())
def test_without_a_depth_limit_the_text_is_json_dumps_with_indent(doc, indent, sort_keys):
    assert json_text(doc, indent=indent, sort_keys=sort_keys) == json.dumps(doc, indent=indent, sort_keys=sort_keys)


@settings(max_examples=300, deadline=None)
@given(documents, st.integers(0, 4), st.booleans())
def test_with_a_depth_limit_the_document_reads_back_equal_and_deep_values_sit_on_one_line(doc, depth, sort_keys):
    text = json_text(doc, indent=2, inline_depth=depth, sort_keys=sort_keys)
    assert json.loads(text) == json.loads(json.dumps(doc))
    for line in text.splitlines():  # indentation never goes deeper than the limit
        assert len(line) - len(line.lstrip(" ")) <= 2 * depth


def test_inline_values_use_spaced_separators_and_outer_levels_are_indented():
    doc = {"passes": [{"index": 0, "waypoints": [{"x_m": 1.5, "ok": True}, {"x_m": -2.0, "ok": None}]}], "n": 1}
    assert json_text(doc, indent=2, inline_depth=3) == (
        '{\n  "passes": [\n    {\n      "index": 0,\n      "waypoints": [{"x_m": 1.5, "ok": true}, '
        '{"x_m": -2.0, "ok": null}]\n    }\n  ],\n  "n": 1\n}')


def test_non_string_keys_are_written_as_json_dumps_writes_them():
    doc = {1: "a", 2.5: "b", True: "c", None: "d"}
    assert json_text(doc) == json.dumps(doc, indent=2)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers_are_refused_at_every_depth(bad):
    for doc in ({"a": bad}, {"a": [{"b": bad}]}):
        for depth in (None, 0, 1, 2):
            with pytest.raises(ValueError):
                json_text(doc, inline_depth=depth)
    with pytest.raises(ValueError):
        json_text({bad: 1})


def test_values_json_cannot_hold_are_refused():
    with pytest.raises(TypeError):
        json_text({"a": {1, 2}})
    with pytest.raises(TypeError):
        json_text({(1, 2): 0})


@settings(max_examples=200, deadline=None)
@given(documents, st.integers(1, 9), st.sampled_from([None, 0, 1, 2]))
def test_written_in_pieces_the_text_is_the_same(doc, chunk_parts, depth):
    pieces: list[str] = []
    write_json_text(doc, pieces.append, indent=2, inline_depth=depth, chunk_parts=chunk_parts)
    assert "".join(pieces) == json_text(doc, indent=2, inline_depth=depth)


def test_a_large_document_goes_out_in_bounded_pieces():
    doc = {"passes": [{"index": k, "waypoints": [{"x_m": float(j)} for j in range(5)]} for k in range(2000)]}
    pieces: list[str] = []
    write_json_text(doc, pieces.append, indent=2, inline_depth=3, chunk_parts=100)
    text = "".join(pieces)
    assert text == json_text(doc, indent=2, inline_depth=3) and len(text) > 200_000
    # a piece holds about chunk_parts strings (plus the rest of one member): never the document
    assert max(len(p) for p in pieces) < 10_000
