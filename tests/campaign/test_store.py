"""The campaign store: schema versions and migrations, refusal of newer stores, idempotent writes, export."""

from __future__ import annotations

import csv
import hashlib
import os
import sqlite3

import pytest

from pihim.campaign.store import APPLICATION_ID, EXPORT_TABLES, MIGRATIONS, SCHEMA_VERSION, open_store
from pihim.errors import PihimInputError

HELIOSTATS = [("5E1", 10.0, 20.0, 3.0), ("5E2", 16.0, 20.0, 3.0), ("6E1", 10.0, 30.0, 3.0)]


def _fill(store):
    cid = store.ensure_campaign("may", field_source="test", field_key="k1", heliostats=HELIOSTATS)
    frames = [(f"{k:04d}", f"frames/{k:04d}.tiff", f"2021-05-13T19:00:0{k}Z", "{}", None) for k in range(4)]
    fid = store.ensure_flight(cid, "f1", "/data/f1", "csv", frames)
    run = store.start_run(cid, {"workers": 1})
    return cid, fid, run


def _frame_ids(store):
    return [r["id"] for r in store.db.execute("SELECT id FROM frame ORDER BY id")]


def test_new_store_has_the_current_schema(tmp_path) -> None:
    with open_store(tmp_path / "c.sqlite") as s:
        assert s.schema_version == SCHEMA_VERSION == 2
        assert s.db.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID
        tables = {r[0] for r in s.db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"campaign", "heliostat", "flight", "frame", "candidate", "observation", "facet_result", "run"} <= tables


def _version_1_store(path) -> None:
    """A store of schema version 1 with one campaign, 'old'."""
    db = sqlite3.connect(path)
    db.executescript(MIGRATIONS[0])
    db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    db.execute("PRAGMA user_version = 1")
    db.execute("INSERT INTO campaign (name, field_source, field_key, created_utc) VALUES ('old', 's', 'k', 'now')")
    db.commit()
    db.close()


def test_version_1_store_is_migrated_and_keeps_its_rows(tmp_path) -> None:
    path = tmp_path / "old.sqlite"
    _version_1_store(path)
    with open_store(path) as s:
        assert s.schema_version == 2
        assert [r["name"] for r in s.campaigns()] == ["old"]
        assert s.db.execute("SELECT count(*) FROM run").fetchone()[0] == 0


def test_newer_schema_refused_and_file_untouched(tmp_path) -> None:
    path = tmp_path / "new.sqlite"
    with open_store(path) as s:
        _fill(s)
        s.db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    with pytest.raises(PihimInputError, match=r"schema 3 is newer than this pihim's \(2\)"):
        open_store(path)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before


def test_not_a_store_refused(tmp_path) -> None:
    (tmp_path / "x.sqlite").write_text("hello, world, this is not SQLite at all")
    with pytest.raises(PihimInputError, match="not an SQLite database"):
        open_store(tmp_path / "x.sqlite")
    other = tmp_path / "other.sqlite"
    db = sqlite3.connect(other)
    db.execute("CREATE TABLE t (a)")
    db.commit()
    db.close()
    with pytest.raises(PihimInputError, match="not a pihim campaign store"):
        open_store(other)
    with pytest.raises(PihimInputError, match="no such campaign store"):
        open_store(tmp_path / "missing.sqlite", create=False)


@pytest.mark.parametrize("readonly", [False, True])
def test_a_store_missing_a_table_is_one_line(tmp_path, readonly) -> None:
    """A store of the current schema with a table dropped (by hand): refused by name, not an SQL error later."""
    path = tmp_path / "c.sqlite"
    open_store(path).close()
    db = sqlite3.connect(path)
    db.execute("DROP TABLE observation")
    db.commit()
    db.close()
    with pytest.raises(PihimInputError, match="a damaged campaign store \\(no table observation\\)"):
        open_store(path, readonly=readonly)


def test_registration_is_idempotent(tmp_path) -> None:
    with open_store(tmp_path / "c.sqlite") as s:
        cid, fid, _ = _fill(s)
        cid2, fid2, _ = _fill(s)
        assert (cid, fid) == (cid2, fid2)
        assert s.db.execute("SELECT count(*) FROM heliostat").fetchone()[0] == 3
        assert s.db.execute("SELECT count(*) FROM frame").fetchone()[0] == 4
        with pytest.raises(PihimInputError, match="another field"):
            s.ensure_campaign("may", field_source="x", field_key="k2", heliostats=HELIOSTATS)


def test_selection_choice_and_observations_upsert(tmp_path) -> None:
    with open_store(tmp_path / "c.sqlite") as s:
        cid, _, run = _fill(s)
        ids = _frame_ids(s)
        scores = [0.3, 0.9, 0.5, 0.7]
        for fid, sc in zip(ids, scores, strict=True):
            cands = [{"hua": "5E1", "target": "6E1", "selected": True, "score": sc},
                     {"hua": "5E2", "target": "6E1", "selected": False, "reason": "HUA not fully in view"}]
            s.record_selection(fid, cands, run_id=run, seconds=0.1)
            s.record_selection(fid, cands, run_id=run, seconds=0.1)  # a rerun: same rows
        assert s.db.execute("SELECT count(*) FROM candidate").fetchone()[0] == 8
        assert s.choose(cid, 2) == 2
        chosen = [r[0] for r in s.db.execute(
            "SELECT frame.frame_key FROM candidate JOIN frame ON frame.id = candidate.frame_id WHERE chosen = 1 "
            "ORDER BY frame.frame_key")]
        assert chosen == ["0001", "0003"]  # scores 0.9 and 0.7
        todo = s.frames_to_inspect(cid)
        assert [len(p) for _, p in todo] == [1, 1]
        c = s.counts(cid)
        assert c["frames"] == {"pending": 0, "selected": 2, "done": 0, "skipped": 2}
        assert c["pairs_skipped_by_reason"] == {"HUA not fully in view": 4}
        for row, pairs in todo:
            obs = [{"hua": h, "target": t, "status": "done", "result": {"facets": []}, "seconds": 1.0} for h, t in pairs]
            s.record_observations(row["id"], obs, run_id=run, parameters={"demosaic": "full"})
            s.record_observations(row["id"], obs, run_id=run, parameters={"demosaic": "full"})
        assert s.db.execute("SELECT count(*) FROM observation").fetchone()[0] == 2
        assert s.frames_to_inspect(cid) == []
        assert s.counts(cid)["frames"]["done"] == 2


def test_a_failed_write_leaves_nothing_half_done(tmp_path) -> None:
    with open_store(tmp_path / "c.sqlite") as s:
        cid, _, run = _fill(s)
        fid = _frame_ids(s)[0]
        s.record_selection(fid, [{"hua": "5E1", "target": "6E1", "selected": True, "score": 1.0}], run_id=run,
                           seconds=0.1)
        s.choose(cid, 3)
        bad = [{"hua": "5E1", "target": "6E1", "status": "done", "result": {}},
               {"hua": "5E1", "target": "6E1", "status": "bogus"}]  # violates the CHECK after the first row
        with pytest.raises(sqlite3.IntegrityError):
            s.record_observations(fid, bad, run_id=run, parameters={})
        assert s.db.execute("SELECT count(*) FROM observation").fetchone()[0] == 0
        assert s.db.execute("SELECT stage FROM frame WHERE id = ?", (fid,)).fetchone()[0] == "selected"


def test_heliostat_results_with_provenance_upserted(tmp_path) -> None:
    with open_store(tmp_path / "c.sqlite") as s:
        cid, _, _ = _fill(s)
        facets = [{"id": 1, "used": True, "az_mrad": 0.5, "el_mrad": -0.2, "points": 40},
                  {"id": 2, "used": False, "reason": "saturated"}]
        for rms in (1.0, 2.0):
            s.record_heliostat(cid, "5E1", facets, frame_ids=["f1/0001"], parameters={"p": 1}, rms_mrad=rms, frames=1)
        rows = s.db.execute("SELECT * FROM facet_result").fetchall()
        assert len(rows) == 2
        assert rows[0]["pihim_version"] and rows[0]["frame_ids"] == '["f1/0001"]' and rows[0]["parameters"] == '{"p":1}'
        assert s.db.execute("SELECT canting_rms_mrad FROM heliostat WHERE name = '5E1'").fetchone()[0] == 2.0


def test_export_csv_and_parquet(tmp_path) -> None:
    with open_store(tmp_path / "c.sqlite") as s:
        cid, _, _ = _fill(s)
        s.record_heliostat(cid, "5E2", [{"id": 1, "used": True, "az_mrad": 0.1, "el_mrad": 0.2}], frame_ids=["a"],
                           parameters={}, rms_mrad=0.2, frames=1)
        paths = s.export(tmp_path / "out")
        assert set(paths) == set(EXPORT_TABLES)
        with open(paths["facets"], newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert len(rows) == 1 and rows[0]["heliostat"] == "5E2" and float(rows[0]["el_mrad"]) == 0.2
        with open(paths["frames"], newline="") as fh:
            assert len(list(csv.DictReader(fh))) == 4
        pq = pytest.importorskip("pyarrow.parquet")
        ppaths = s.export(tmp_path / "pq", fmt="parquet")
        t = pq.read_table(ppaths["facets"])
        assert t.num_rows == 1 and t.column("heliostat").to_pylist() == ["5E2"]
        with pytest.raises(PihimInputError, match="csv or parquet"):
            s.export(tmp_path / "x", fmt="xlsx")


def test_read_only_open_refuses_what_is_not_a_store_and_changes_nothing(tmp_path) -> None:
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    bare = tmp_path / "bare.sqlite"
    db = sqlite3.connect(bare)
    db.execute("PRAGMA user_version = 0")
    db.execute("VACUUM")  # a valid SQLite file without a table
    db.close()
    other = tmp_path / "other.sqlite"
    db = sqlite3.connect(other)
    db.execute("CREATE TABLE t (a)")
    db.commit()
    db.close()
    for path, msg in ((empty, "an empty file, not a campaign store"),
                      (bare, "an empty SQLite database, not a campaign store"),
                      (other, "not a pihim campaign store"),
                      (tmp_path / "missing.sqlite", "no such campaign store")):
        before = path.read_bytes() if path.exists() else None
        with pytest.raises(PihimInputError, match=msg):
            open_store(path, readonly=True)
        assert (path.read_bytes() if path.exists() else None) == before  # not turned into a store
    assert not (tmp_path / "missing.sqlite").exists()


def test_read_only_store_reads_and_never_writes(tmp_path) -> None:
    path = tmp_path / "c.sqlite"
    with open_store(path) as s:
        _fill(s)
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    with open_store(path, readonly=True) as s:
        assert [r["name"] for r in s.campaigns()] == ["may"]
        assert len(s.table_rows("frames")[1]) == 4
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            s.ensure_campaign("june", field_source="test", field_key="k1", heliostats=HELIOSTATS)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere: the folder would not be read-only")
def test_read_only_store_in_a_folder_the_user_cannot_write(tmp_path) -> None:
    # a WAL-mode store closed cleanly (no -wal file) in a read-only folder: SQLite's mode=ro cannot make the
    # -shm file ("unable to open database file"); the store is read as immutable instead
    folder = tmp_path / "ro"
    folder.mkdir()
    path = folder / "c.sqlite"
    with open_store(path) as s:
        _fill(s)
    assert not path.with_name("c.sqlite-wal").exists()
    folder.chmod(0o555)
    try:
        with open_store(path, readonly=True) as s:
            assert [r["name"] for r in s.campaigns()] == ["may"]
            assert len(s.table_rows("frames")[1]) == 4
    finally:
        folder.chmod(0o755)


def test_read_only_version_1_store_is_migrated_in_a_temporary_copy_only(tmp_path) -> None:
    path = tmp_path / "old.sqlite"
    _version_1_store(path)
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    with open_store(path, readonly=True) as s:
        assert s.schema_version == 2 and [r["name"] for r in s.campaigns()] == ["old"]
        assert s.table_rows("runs")[1] == []  # the schema 2 table, in the copy
        with pytest.raises(sqlite3.OperationalError, match="readonly"):  # the copy takes no writes either
            s.ensure_campaign("new", field_source="x", field_key="k", heliostats=[("A", 0.0, 0.0, 0.0)])
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 1
