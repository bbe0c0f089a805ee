"""build_plan and export_all with forked workers: the plan and its files to the byte, whatever the workers."""

import functools
import sys

import pytest

from pihim import _forked
from pihim.errors import PihimInputError
from pihim.field import nsttf_like_field
from pihim.planning import facet_captures, facets, pipeline, scoring, ufacet
from pihim.planning.export import export_all
from pihim.planning import export as export_module
from pihim.sky.sun import NSTTF, parse_time

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")
WHEN = parse_time("2021-05-13T10:00-06:00")


def _without_timings(plan) -> dict:
    d = plan.to_dict()
    d["summary"].pop("seconds")
    return d


@pytest.fixture(scope="module")
def field():
    return nsttf_like_field()


@linux
def test_workers_give_the_one_process_plan_and_files(field, tmp_path, monkeypatch):
    """Every stage that shares work among workers does (small pieces on this small field), and nothing changes."""
    one = pipeline.build_plan(field, WHEN, NSTTF, workers=1)  # whole: one group, one chunk
    files_1 = export_all(one, tmp_path / "one", field=field, workers=1)
    monkeypatch.setattr(facets, "_CHUNK", 100)  # the facet report in several chunks of captures
    monkeypatch.setattr(facet_captures, "_BATCHES_PER_PIECE", 2)
    monkeypatch.setattr(ufacet, "_config_scores", functools.partial(ufacet._config_scores, chunk=3000))
    monkeypatch.setattr(ufacet, "_FLUX_PIECE", 500)  # the flux samples along the passes in several pieces
    monkeypatch.setattr(pipeline, "score_passes", functools.partial(scoring.score_passes, batch_images=60))
    monkeypatch.setattr(export_module, "_FLIGHTS_PER_PIECE", 1)
    forked = []
    imap_unordered = _forked.imap_unordered

    def spy(job, n, workers, *, what="pieces"):
        if _forked.can_fork(workers, n):
            forked.append(what)
        return imap_unordered(job, n, workers, what=what)

    monkeypatch.setattr(_forked, "imap_unordered", spy)
    start = _forked.start

    def spy_start(job, n, workers, *, what="pieces"):
        started = start(job, n, workers, what=what)
        if started.running:
            forked.append(what + " (started)")
        return started

    monkeypatch.setattr(_forked, "start", spy_start)
    assert pipeline.build_plan(field, WHEN, NSTTF, workers=1, facet_report=False).passes == one.passes
    assert forked == []
    two = pipeline.build_plan(field, WHEN, NSTTF, workers=2)
    lines = forked.count("chunks of line settings")
    assert lines >= 2 and forked[lines:] == ["flux samples", "groups of passes", "batches of HUAs",
                                             "HUAs' own lines", "chunks of captures (started)", "groups of passes"]
    assert len(one.flights) >= 2 and _without_timings(two) == _without_timings(one)
    files_2 = export_all(one, tmp_path / "two", field=field, workers=2)
    assert forked[lines + 6:] == ["files"]
    assert files_1.keys() == files_2.keys() and len(files_1) >= 3 + 3 * len(one.flights)
    for key, path in files_1.items():
        assert files_2[key].read_bytes() == path.read_bytes(), key


@linux
def test_a_flight_over_the_item_limit_is_named_in_flight_order_with_workers(field, tmp_path, monkeypatch):
    monkeypatch.setattr(export_module, "_FLIGHTS_PER_PIECE", 1)
    plan = pipeline.build_plan(field, WHEN, NSTTF, facet_report=False)
    assert len(plan.flights) >= 2
    with pytest.raises(PihimInputError, match=r"^flight 1 needs \d+ mission items, more than the limit of 10"):
        export_all(plan, tmp_path / "out", max_mission_items=10, workers=2)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("workers", [0, 1.0, "2"])
def test_bad_worker_counts_are_refused_before_planning(field, workers):
    with pytest.raises(PihimInputError, match="workers"):
        pipeline.build_plan(field, WHEN, NSTTF, workers=workers)


def test_time_and_site_as_text_and_a_site_that_is_none_of_them(field):
    """site='nsttf' was refused as a bad 'origin' (sun_position takes it); a text time was an AttributeError."""
    plan = pipeline.build_plan(field, "2021-05-13T10:00-06:00", "nsttf", facet_report=False)
    assert plan.time_iso == WHEN.isoformat() and plan.site == NSTTF.as_dict()
    with pytest.raises(PihimInputError, match="site must be a pihim.sky.sun.Site, 'nsttf' or 'LAT,LON,H', got 3"):
        pipeline.build_plan(field, WHEN, 3)
    with pytest.raises(PihimInputError, match="no UTC offset"):
        pipeline.build_plan(field, "2021-05-13T13:00", NSTTF)


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=linux)])
def test_an_interrupted_export_leaves_the_folder_as_it_was(field, tmp_path, monkeypatch, workers):
    """Files are written to temporaries by the process rendering them: an interruption removes them all,
    those of pieces finished in workers after it included, and keeps what was there before."""
    monkeypatch.setattr(export_module, "_FLIGHTS_PER_PIECE", 1)
    plan = pipeline.build_plan(field, WHEN, NSTTF, facet_report=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "plan.json").write_text("an earlier plan")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(export_module, "plan_png_bytes", interrupted)  # the third piece, after plan.json's
    with pytest.raises(KeyboardInterrupt):
        export_all(plan, out, field=field, workers=workers)
    assert [p.name for p in out.iterdir()] == ["plan.json"] and (out / "plan.json").read_text() == "an earlier plan"
    with pytest.raises(KeyboardInterrupt):
        export_all(plan, tmp_path / "new", field=field, workers=workers)
    assert not (tmp_path / "new").exists()


@linux
def test_a_refused_flight_with_workers_leaves_an_existing_folder_untouched(field, tmp_path, monkeypatch):
    monkeypatch.setattr(export_module, "_FLIGHTS_PER_PIECE", 1)
    plan = pipeline.build_plan(field, WHEN, NSTTF, facet_report=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("kept")
    with pytest.raises(PihimInputError, match="more than the limit of 10"):
        export_all(plan, out, max_mission_items=10, workers=2)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


@linux
def test_a_worker_that_dies_while_writing_leaves_no_temporary(field, tmp_path, monkeypatch):
    """Its pieces run again here (with a warning) and the export succeeds; its half-written temporary goes."""
    import os
    import signal

    from pihim.planning.export import kml

    monkeypatch.setattr(export_module, "_FLIGHTS_PER_PIECE", 1)
    plan = pipeline.build_plan(field, WHEN, NSTTF, facet_report=False)
    parent, real = os.getpid(), kml.write_kml_text

    def dying(plan, write, **kwargs):
        if os.getpid() != parent:
            write("<?xml, and then the worker is killed")
            os.kill(os.getpid(), signal.SIGKILL)
        real(plan, write, **kwargs)

    monkeypatch.setattr(export_module, "write_kml_text", dying)
    with pytest.warns(RuntimeWarning, match="a worker process died"):
        files = export_all(plan, tmp_path / "out", field=field, workers=2)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in files.values())
    assert files["kml"].read_text() == kml.kml_text(plan, field=field)


def test_an_interruption_during_the_renames_removes_only_the_temporaries(field, tmp_path, monkeypatch):
    """The files renamed before it stay renamed (each replaced its earlier version for good), a linked name stays
    a link, and the earlier files not yet reached stay as they were."""
    import os

    plan = pipeline.build_plan(field, WHEN, NSTTF, facet_report=False)
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    (elsewhere / "plan.kml").write_text("an earlier map")
    (out / "plan.kml").symlink_to(elsewhere / "plan.kml")
    (out / "flight_01.plan").write_text("an earlier mission")
    real, calls = os.replace, []

    def replace(src, dst):
        calls.append(dst)
        if len(calls) == 3:  # plan.json and plan.kml are renamed, then Ctrl-C
            raise KeyboardInterrupt
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        export_all(plan, out, field=field, workers=1)
    assert sorted(p.name for p in out.iterdir()) == ["flight_01.plan", "plan.json", "plan.kml"]
    assert (out / "plan.kml").is_symlink() and (out / "plan.kml").read_text().startswith("<?xml")
    assert (out / "flight_01.plan").read_text() == "an earlier mission"
