"""The campaign results store: one SQLite file, versioned, migrated, idempotent.

What a campaign keeps (tables; every name is unique within its parent, so
writing the same thing twice updates one row instead of adding a second):

* ``campaign`` -- a named inspection of one field (``name`` unique);
* ``heliostat`` -- the field's heliostats per campaign, with the per-heliostat
  summary once computed (facets measured, canting RMS, frames used);
* ``flight`` -- a flight directory of the campaign;
* ``frame`` -- a frame of a flight (``frame_key`` unique per flight) with its
  matched pose and its stage: ``pending`` -> ``selected`` (pair selection
  done) -> ``done`` (every chosen pair inspected), or ``skipped`` with a reason;
  ``run_id`` is the run that finished it;
* ``candidate`` -- a HUA-target pair a frame shows, selected or skipped with
  the reason, its score, and whether it was ``chosen`` for canting;
* ``observation`` -- the canting of one pair from one frame (the full
  :class:`~pihim.inspection.canting.CantingResult` as JSON) or the failure;
* ``facet_result`` -- the combined canting of each facet of each heliostat,
  with its **provenance**: the pihim version, the parameters and the frame
  ids it was combined from;
* ``run`` (schema 2) -- every ``pihim campaign run``: start, end, version,
  parameters, host, counts.

Every write of a unit of work (one frame's selection, one frame's
observations, one heliostat's combination) is one transaction, so a process
killed at any instant (``kill -9``) leaves the store as it was before or
after that unit, never between; SQLite's write-ahead log guarantees it [1]_
(the store runs in WAL mode with ``synchronous = NORMAL``: committed
transactions survive a killed process; a power cut may lose the last ones,
never consistency). Rows are written with ``INSERT ... ON CONFLICT DO UPDATE`` on their
unique keys: a rerun never duplicates.

The schema version is SQLite's ``user_version``; :data:`MIGRATIONS` brings
an older store up to date in one transaction; a store written by a newer
pihim is refused (``PihimInputError``), never changed.

References
----------
.. [1] SQLite, "Atomic Commit In SQLite", https://sqlite.org/atomiccommit.html
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import socket
import sqlite3
import time as _time
from collections.abc import Iterable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from pihim.errors import PihimInputError

__all__ = ["APPLICATION_ID", "EXPORT_TABLES", "MIGRATIONS", "SCHEMA_VERSION", "CampaignStore", "open_store"]

#: SQLite ``application_id`` of a pihim store ("pihm").
APPLICATION_ID = 0x7069686D

_V1 = """
CREATE TABLE campaign (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    field_source TEXT NOT NULL,
    field_key TEXT NOT NULL,
    created_utc TEXT NOT NULL
);
CREATE TABLE heliostat (
    id INTEGER PRIMARY KEY,
    campaign_id INTEGER NOT NULL REFERENCES campaign(id),
    name TEXT NOT NULL,
    x_m REAL NOT NULL, y_m REAL NOT NULL, z_m REAL NOT NULL,
    facets_used INTEGER, facets_total INTEGER, canting_rms_mrad REAL, frames INTEGER,
    UNIQUE (campaign_id, name)
);
CREATE TABLE flight (
    id INTEGER PRIMARY KEY,
    campaign_id INTEGER NOT NULL REFERENCES campaign(id),
    name TEXT NOT NULL,
    path TEXT NOT NULL,
    log_kind TEXT NOT NULL,
    frame_count INTEGER NOT NULL,
    UNIQUE (campaign_id, name)
);
CREATE TABLE frame (
    id INTEGER PRIMARY KEY,
    flight_id INTEGER NOT NULL REFERENCES flight(id),
    frame_key TEXT NOT NULL,
    file TEXT NOT NULL,
    time_utc TEXT NOT NULL,
    pose TEXT,
    stage TEXT NOT NULL DEFAULT 'pending' CHECK (stage IN ('pending', 'selected', 'done', 'skipped')),
    reason TEXT,
    run_id INTEGER,
    seconds REAL,
    UNIQUE (flight_id, frame_key)
);
CREATE TABLE candidate (
    id INTEGER PRIMARY KEY,
    frame_id INTEGER NOT NULL REFERENCES frame(id),
    hua TEXT NOT NULL,
    target TEXT NOT NULL,
    selected INTEGER NOT NULL,
    reason TEXT,
    score REAL,
    metrics TEXT,
    chosen INTEGER NOT NULL DEFAULT 0,
    UNIQUE (frame_id, hua, target)
);
CREATE TABLE observation (
    id INTEGER PRIMARY KEY,
    frame_id INTEGER NOT NULL REFERENCES frame(id),
    hua TEXT NOT NULL,
    target TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('done', 'failed')),
    reason TEXT,
    result TEXT,
    seconds REAL,
    pihim_version TEXT NOT NULL,
    parameters TEXT NOT NULL,
    UNIQUE (frame_id, hua, target)
);
CREATE TABLE facet_result (
    id INTEGER PRIMARY KEY,
    heliostat_id INTEGER NOT NULL REFERENCES heliostat(id),
    facet INTEGER NOT NULL,
    used INTEGER NOT NULL,
    reason TEXT,
    az_mrad REAL, el_mrad REAL, az_sigma_mrad REAL, el_sigma_mrad REAL,
    points INTEGER,
    frame_ids TEXT NOT NULL,
    pihim_version TEXT NOT NULL,
    parameters TEXT NOT NULL,
    computed_utc TEXT NOT NULL,
    UNIQUE (heliostat_id, facet)
);
CREATE INDEX frame_stage ON frame (stage);
CREATE INDEX candidate_pair ON candidate (hua, target);
"""

_V2 = """
CREATE TABLE run (
    id INTEGER PRIMARY KEY,
    campaign_id INTEGER NOT NULL REFERENCES campaign(id),
    started_utc TEXT NOT NULL,
    finished_utc TEXT,
    pihim_version TEXT NOT NULL,
    parameters TEXT NOT NULL,
    host TEXT NOT NULL,
    frames_processed INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX observation_hua ON observation (hua);
"""

#: Migrations: ``MIGRATIONS[k]`` takes a store from schema ``k`` to ``k + 1`` (0 is a new file).
MIGRATIONS: tuple[str, ...] = (_V1, _V2)
#: The tables a store of the current schema has (from :data:`MIGRATIONS`).
_TABLES = frozenset(re.findall(r"CREATE TABLE (?:IF NOT EXISTS )?(\w+)", "".join(MIGRATIONS)))
#: Schema version written by this pihim.
SCHEMA_VERSION = len(MIGRATIONS)

#: Tables written by :meth:`CampaignStore.export` (``facets`` joins facet results with names).
EXPORT_TABLES: tuple[str, ...] = ("campaigns", "flights", "frames", "candidates", "observations", "heliostats",
                                  "facets", "runs")


def utc_now() -> str:
    """Now as ISO 8601 UTC, seconds."""
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _version() -> str:
    from pihim import __version__

    return __version__


def _dumps(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, allow_nan=False, separators=(",", ":"))


class CampaignStore:
    """An open campaign store (use :func:`open_store`, or as a context manager).

    All writes go through methods that each commit one transaction.

    Parameters
    ----------
    path : path-like
    create : bool
        Create the store if the file is missing (else a one-line error).
    readonly : bool
        Open the file read-only (SQLite ``mode=ro``): nothing is ever written
        to it, a missing, empty (0-byte) or empty-SQLite file is refused
        instead of becoming a store, and an older schema is migrated in a
        private temporary copy (SQLite's temporary database: on disk,
        deleted when the store closes), never in the file. Writing methods then fail.
    """

    def __init__(self, path: str | os.PathLike[str], *, create: bool = True, readonly: bool = False) -> None:
        self.path = Path(path)
        self.readonly = readonly
        create = create and not readonly
        if self.path.is_dir():
            raise PihimInputError(f"{self.path}: is a directory, not a campaign store")
        if self.path.exists() and not self.path.is_file():
            raise PihimInputError(f"{self.path}: not a regular file (a FIFO, device or socket), not a campaign store")
        if not self.path.exists():
            if not create:
                raise PihimInputError(f"{self.path}: no such campaign store")
            if not self.path.parent.is_dir():
                raise PihimInputError(f"{self.path}: the directory {self.path.parent} does not exist")
        elif self.path.stat().st_size > 0:
            with open(self.path, "rb") as fh:
                if fh.read(16) != b"SQLite format 3\x00":
                    raise PihimInputError(f"{self.path}: not a campaign store (not an SQLite database)")
        elif readonly:
            raise PihimInputError(f"{self.path}: an empty file, not a campaign store (pihim campaign run makes one)")
        try:
            if readonly:
                self.db = self._connect_readonly()
            else:
                self.db = sqlite3.connect(str(self.path), timeout=30.0, isolation_level=None)
            self.db.row_factory = sqlite3.Row
            self.db.execute("PRAGMA foreign_keys = ON")
            self._check_and_migrate()
            if readonly:
                return
            if self.path.stat().st_size and self.db.execute("PRAGMA journal_mode").fetchone()[0] != "wal":
                self.db.execute("PRAGMA journal_mode = WAL")
            # WAL with synchronous NORMAL: a commit survives the process being killed (not a power cut) and
            # costs no fsync; one commit per frame would otherwise bound the run at the disk's fsync rate
            self.db.execute("PRAGMA synchronous = NORMAL")
        except sqlite3.DatabaseError as exc:
            raise PihimInputError(f"{self.path}: not a usable campaign store ({exc})") from None

    def _connect_readonly(self) -> sqlite3.Connection:
        """SQLite ``mode=ro``; a WAL-mode store in a folder this user cannot write opened as ``immutable``.

        ``mode=ro`` on a store in WAL mode needs its ``-shm`` file, which SQLite cannot create in a read-only
        folder (a read-only medium, another user's campaign): "unable to open database file". Where no ``-wal``
        file holds changes, the store file alone is the whole store and is read as immutable; with one, the
        error stands (the changes are in the ``-wal`` file, which only a writable folder lets SQLite read).
        """
        uri = self.path.resolve().as_uri()
        db = sqlite3.connect(uri + "?mode=ro", uri=True, timeout=30.0, isolation_level=None)
        try:
            db.execute("PRAGMA user_version").fetchone()
            return db
        except sqlite3.OperationalError as exc:
            db.close()
            wal = self.path.with_name(self.path.name + "-wal")
            if "unable to open" not in str(exc) or (wal.exists() and wal.stat().st_size > 0):
                raise  # a lock held by a writer, or changes in the -wal file: never read the file as immutable
        return sqlite3.connect(uri + "?mode=ro&immutable=1", uri=True, timeout=30.0, isolation_level=None)

    # ------------------------------------------------------------------ schema

    def _check_and_migrate(self) -> None:
        version = int(self.db.execute("PRAGMA user_version").fetchone()[0])
        app = int(self.db.execute("PRAGMA application_id").fetchone()[0])
        tables = self.db.execute("SELECT count(*) FROM sqlite_master WHERE type = 'table'").fetchone()[0]
        if app not in (0, APPLICATION_ID) or (app == 0 and (version or tables)):
            raise PihimInputError(f"{self.path}: an SQLite database that is not a pihim campaign store")
        if version > SCHEMA_VERSION:
            raise PihimInputError(
                f"{self.path}: campaign store schema {version} is newer than this pihim's ({SCHEMA_VERSION}); "
                "upgrade pihim to use it (the store was not changed)"
            )
        if version == SCHEMA_VERSION:
            self._check_tables()
            return
        if self.readonly:
            if version == 0:
                raise PihimInputError(f"{self.path}: an empty SQLite database, not a campaign store "
                                      "(pihim campaign run makes one)")
            # an older store read without touching it: migrate a copy in SQLite's private temporary database
            # (the empty name: on disk in the temporary directory, deleted on close; RAM only for its page cache),
            # or in memory where the temporary directory cannot hold it
            try:
                copy = sqlite3.connect("", isolation_level=None)
                self.db.backup(copy)
            except sqlite3.OperationalError:
                copy.close()
                copy = sqlite3.connect(":memory:", isolation_level=None)
                self.db.backup(copy)
            self.db.close()
            self.db = copy
            self.db.row_factory = sqlite3.Row
            self.db.execute("PRAGMA foreign_keys = ON")
        self.db.execute("BEGIN IMMEDIATE")
        try:
            version = int(self.db.execute("PRAGMA user_version").fetchone()[0])  # another process may have migrated
            for k in range(version, SCHEMA_VERSION):
                for stmt in MIGRATIONS[k].split(";"):
                    if stmt.strip():
                        self.db.execute(stmt)
            self.db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            self.db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            self.db.execute("COMMIT")
        except BaseException:
            self.db.execute("ROLLBACK")
            raise
        if self.readonly:
            self.db.execute("PRAGMA query_only = ON")  # the migrated copy is read-only too: writes fail

    def _check_tables(self) -> None:
        """A store of the current schema whose tables are not all there (edited by hand, damaged): one line."""
        have = {r[0] for r in self.db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        missing = sorted(_TABLES - have)
        if missing:
            raise PihimInputError(f"{self.path}: a damaged campaign store (no table {', '.join(missing)}); "
                                  "start a new one with pihim campaign run --store")

    @property
    def schema_version(self) -> int:
        return int(self.db.execute("PRAGMA user_version").fetchone()[0])

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> CampaignStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _tx(self) -> _Transaction:
        return _Transaction(self.db)

    # ------------------------------------------------------------------ registration (idempotent)

    def ensure_campaign(self, name: str, *, field_source: str, field_key: str,
                        heliostats: Sequence[tuple[str, float, float, float]]) -> int:
        """The campaign's id, creating it and its heliostats if new.

        Raises
        ------
        PihimInputError
            A campaign of that name exists for another field (``field_key`` differs).
        """
        row = self.db.execute("SELECT id, field_key FROM campaign WHERE name = ?", (name,)).fetchone()
        if row is not None:
            if row["field_key"] != field_key:
                raise PihimInputError(f"campaign {name!r} in {self.path} is of another field; give another --campaign")
            return int(row["id"])
        with self._tx():
            cur = self.db.execute(
                "INSERT INTO campaign (name, field_source, field_key, created_utc) VALUES (?, ?, ?, ?) "
                "ON CONFLICT (name) DO NOTHING", (name, field_source, field_key, utc_now()))
            cid = cur.lastrowid if cur.rowcount else self.db.execute(
                "SELECT id FROM campaign WHERE name = ?", (name,)).fetchone()[0]
            self.db.executemany(
                "INSERT INTO heliostat (campaign_id, name, x_m, y_m, z_m) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT (campaign_id, name) DO NOTHING",
                [(cid, n, float(x), float(y), float(z)) for n, x, y, z in heliostats])
        return int(cid)

    def ensure_flight(self, campaign_id: int, name: str, path: str, log_kind: str,
                      frames: Sequence[tuple[str, str, str, str | None, str | None]]) -> int:
        """The flight's id, registering it and its frames ``(key, file, time_utc, pose_json, skip_reason)``.

        Frames already registered are left as they are (their stage is kept).
        """
        with self._tx():
            self.db.execute(
                "INSERT INTO flight (campaign_id, name, path, log_kind, frame_count) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT (campaign_id, name) DO UPDATE SET path = excluded.path",
                (campaign_id, name, path, log_kind, len(frames)))
            fid = int(self.db.execute("SELECT id FROM flight WHERE campaign_id = ? AND name = ?",
                                      (campaign_id, name)).fetchone()[0])
            self.db.executemany(
                "INSERT INTO frame (flight_id, frame_key, file, time_utc, pose, stage, reason) "
                "VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (flight_id, frame_key) DO NOTHING",
                [(fid, k, f, t, p, "skipped" if why else "pending", why) for k, f, t, p, why in frames])
        return fid

    def start_run(self, campaign_id: int, parameters: Mapping[str, Any]) -> int:
        with self._tx():
            cur = self.db.execute(
                "INSERT INTO run (campaign_id, started_utc, pihim_version, parameters, host) VALUES (?, ?, ?, ?, ?)",
                (campaign_id, utc_now(), _version(), _dumps(dict(parameters)), socket.gethostname()))
        return int(cur.lastrowid)

    def finish_run(self, run_id: int, frames_processed: int) -> None:
        with self._tx():
            self.db.execute("UPDATE run SET finished_utc = ?, frames_processed = ? WHERE id = ?",
                            (utc_now(), int(frames_processed), run_id))

    # ------------------------------------------------------------------ units of work

    def pending_frames(self, campaign_id: int) -> list[sqlite3.Row]:
        """Frames whose selection is still to do: ``pending``, or skipped as unreadable (tried again)."""
        return self.db.execute(
            "SELECT frame.*, flight.name AS flight_name, flight.path AS flight_path FROM frame "
            "JOIN flight ON flight.id = frame.flight_id WHERE flight.campaign_id = ? AND (frame.stage = 'pending' "
            "OR (frame.stage = 'skipped' AND frame.reason LIKE 'unreadable: %')) ORDER BY frame.id",
            (campaign_id,)).fetchall()

    def record_selection(self, frame_id: int, candidates: Iterable[Mapping[str, Any]], *, run_id: int,
                         seconds: float, skip_reason: str | None = None) -> None:
        """One frame's pair selection, in one transaction: candidates upserted, stage set."""
        rows = [(frame_id, c["hua"], c["target"], int(bool(c["selected"])), c.get("reason"),
                 None if c.get("score") is None else float(c["score"]), _dumps(c.get("metrics", {})))
                for c in candidates]
        any_selected = any(r[3] for r in rows)
        with self._tx():
            self.db.executemany(
                "INSERT INTO candidate (frame_id, hua, target, selected, reason, score, metrics) "
                "VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (frame_id, hua, target) DO UPDATE SET "
                "selected = excluded.selected, reason = excluded.reason, score = excluded.score, "
                "metrics = excluded.metrics", rows)
            stage = "selected" if any_selected else "skipped"
            reason = None if any_selected else (skip_reason or ("no HUA-target pair in view" if not rows
                                                                else "no pair passed the selection"))
            self.db.execute("UPDATE frame SET stage = ?, reason = ?, run_id = ?, seconds = ? WHERE id = ?",
                            (stage, reason, run_id, float(seconds), frame_id))

    def choose(self, campaign_id: int, frames_per_pair: int) -> int:
        """Mark the best ``frames_per_pair`` selected frames of each pair ``chosen`` (score, then frame id).

        Deterministic, so a rerun chooses the same frames (plus those selected
        since). Returns the number of chosen candidates.
        """
        with self._tx():
            self.db.execute(
                "UPDATE candidate SET chosen = 0 WHERE frame_id IN (SELECT frame.id FROM frame JOIN flight ON "
                "flight.id = frame.flight_id WHERE flight.campaign_id = ?)", (campaign_id,))
            self.db.execute(
                """UPDATE candidate SET chosen = 1 WHERE id IN (
                     SELECT id FROM (
                       SELECT candidate.id AS id, ROW_NUMBER() OVER (
                         PARTITION BY hua, target ORDER BY score DESC, frame_id ASC) AS k
                       FROM candidate JOIN frame ON frame.id = candidate.frame_id
                       JOIN flight ON flight.id = frame.flight_id
                       WHERE flight.campaign_id = ? AND candidate.selected = 1)
                     WHERE k <= ?)""", (campaign_id, int(frames_per_pair)))
            # a frame whose selected pairs were all left to better frames is finished
            self.db.execute(
                """UPDATE frame SET stage = 'skipped', reason = 'its pairs are imaged better in other frames'
                   WHERE stage = 'selected' AND flight_id IN (SELECT id FROM flight WHERE campaign_id = ?)
                   AND NOT EXISTS (SELECT 1 FROM candidate c WHERE c.frame_id = frame.id AND c.chosen = 1)""",
                (campaign_id,))
            n = self.db.execute(
                "SELECT count(*) FROM candidate JOIN frame ON frame.id = candidate.frame_id JOIN flight ON "
                "flight.id = frame.flight_id WHERE flight.campaign_id = ? AND chosen = 1", (campaign_id,)).fetchone()[0]
        return int(n)

    def frames_to_inspect(self, campaign_id: int) -> list[tuple[sqlite3.Row, list[tuple[str, str]]]]:
        """Frames with chosen pairs that have no observation yet, each with those pairs."""
        rows = self.db.execute(
            """SELECT frame.*, flight.path AS flight_path, flight.name AS flight_name,
                      candidate.hua AS hua, candidate.target AS target FROM candidate
               JOIN frame ON frame.id = candidate.frame_id JOIN flight ON flight.id = frame.flight_id
               WHERE flight.campaign_id = ? AND candidate.chosen = 1 AND NOT EXISTS (
                 SELECT 1 FROM observation o WHERE o.frame_id = frame.id AND o.hua = candidate.hua
                 AND o.target = candidate.target)
               ORDER BY frame.id, candidate.hua, candidate.target""", (campaign_id,)).fetchall()
        out: dict[int, tuple[sqlite3.Row, list[tuple[str, str]]]] = {}
        for r in rows:
            out.setdefault(int(r["id"]), (r, []))[1].append((r["hua"], r["target"]))
        return list(out.values())

    def record_observations(self, frame_id: int, observations: Iterable[Mapping[str, Any]], *, run_id: int,
                            parameters: Mapping[str, Any]) -> None:
        """One frame's inspections, in one transaction; the frame is ``done`` when all its chosen pairs are."""
        version = _version()
        params = _dumps(dict(parameters))
        rows = [(frame_id, o["hua"], o["target"], o["status"], o.get("reason"),
                 None if o.get("result") is None else _dumps(o["result"]), float(o.get("seconds") or 0.0),
                 version, params) for o in observations]
        with self._tx():
            self.db.executemany(
                "INSERT INTO observation (frame_id, hua, target, status, reason, result, seconds, pihim_version, "
                "parameters) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (frame_id, hua, target) DO UPDATE SET "
                "status = excluded.status, reason = excluded.reason, result = excluded.result, "
                "seconds = excluded.seconds, pihim_version = excluded.pihim_version, "
                "parameters = excluded.parameters", rows)
            left = self.db.execute(
                "SELECT count(*) FROM candidate c WHERE c.frame_id = ? AND c.chosen = 1 AND NOT EXISTS ("
                "SELECT 1 FROM observation o WHERE o.frame_id = c.frame_id AND o.hua = c.hua AND o.target = c.target)",
                (frame_id,)).fetchone()[0]
            if left == 0:
                self.db.execute("UPDATE frame SET stage = 'done', run_id = ? WHERE id = ?", (run_id, frame_id))

    def observations_by_hua(self, campaign_id: int) -> dict[str, list[sqlite3.Row]]:
        rows = self.db.execute(
            """SELECT observation.*, frame.frame_key, flight.name AS flight_name FROM observation
               JOIN frame ON frame.id = observation.frame_id JOIN flight ON flight.id = frame.flight_id
               WHERE flight.campaign_id = ? AND observation.status = 'done' ORDER BY observation.id""",
            (campaign_id,)).fetchall()
        out: dict[str, list[sqlite3.Row]] = {}
        for r in rows:
            out.setdefault(r["hua"], []).append(r)
        return out

    def record_heliostat(self, campaign_id: int, name: str, facets: Sequence[Mapping[str, Any]], *,
                         frame_ids: Sequence[str], parameters: Mapping[str, Any], rms_mrad: float | None,
                         frames: int) -> None:
        """One heliostat's combined canting per facet (with provenance) and its summary, in one transaction."""
        hid = self.db.execute("SELECT id FROM heliostat WHERE campaign_id = ? AND name = ?",
                              (campaign_id, name)).fetchone()
        if hid is None:
            raise PihimInputError(f"heliostat {name} is not in the campaign's field")
        version, params, now, ids = _version(), _dumps(dict(parameters)), utc_now(), _dumps(list(frame_ids))
        rows = [(hid[0], int(f["id"]), int(bool(f["used"])), f.get("reason"), f.get("az_mrad"), f.get("el_mrad"),
                 f.get("az_sigma_mrad"), f.get("el_sigma_mrad"), int(f.get("points") or 0), ids, version, params, now)
                for f in facets]
        used = sum(1 for f in facets if f["used"])
        with self._tx():
            self.db.executemany(
                "INSERT INTO facet_result (heliostat_id, facet, used, reason, az_mrad, el_mrad, az_sigma_mrad, "
                "el_sigma_mrad, points, frame_ids, pihim_version, parameters, computed_utc) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (heliostat_id, facet) DO UPDATE SET "
                "used = excluded.used, reason = excluded.reason, az_mrad = excluded.az_mrad, "
                "el_mrad = excluded.el_mrad, az_sigma_mrad = excluded.az_sigma_mrad, "
                "el_sigma_mrad = excluded.el_sigma_mrad, points = excluded.points, frame_ids = excluded.frame_ids, "
                "pihim_version = excluded.pihim_version, parameters = excluded.parameters, "
                "computed_utc = excluded.computed_utc", rows)
            self.db.execute("UPDATE heliostat SET facets_used = ?, facets_total = ?, canting_rms_mrad = ?, frames = ? "
                            "WHERE id = ?", (used, len(facets), rms_mrad, int(frames), hid[0]))

    # ------------------------------------------------------------------ reading

    def campaigns(self) -> list[sqlite3.Row]:
        return self.db.execute("SELECT * FROM campaign ORDER BY id").fetchall()

    def counts(self, campaign_id: int) -> dict[str, Any]:
        """Frames by stage, skip reasons counted, candidates, observations, heliostats measured."""
        q = self.db.execute
        stages = {r[0]: r[1] for r in q(
            "SELECT stage, count(*) FROM frame JOIN flight ON flight.id = frame.flight_id WHERE campaign_id = ? "
            "GROUP BY stage", (campaign_id,))}
        frame_reasons = {r[0]: r[1] for r in q(
            "SELECT reason, count(*) FROM frame JOIN flight ON flight.id = frame.flight_id WHERE campaign_id = ? "
            "AND stage = 'skipped' GROUP BY reason ORDER BY count(*) DESC", (campaign_id,))}
        pair_reasons = {r[0]: r[1] for r in q(
            "SELECT candidate.reason, count(*) FROM candidate JOIN frame ON frame.id = candidate.frame_id JOIN flight "
            "ON flight.id = frame.flight_id WHERE campaign_id = ? AND selected = 0 GROUP BY candidate.reason "
            "ORDER BY count(*) DESC", (campaign_id,))}
        obs = {r[0]: r[1] for r in q(
            "SELECT status, count(*) FROM observation JOIN frame ON frame.id = observation.frame_id JOIN flight ON "
            "flight.id = frame.flight_id WHERE campaign_id = ? GROUP BY status", (campaign_id,))}
        cand = q("SELECT count(*), coalesce(sum(selected), 0), coalesce(sum(chosen), 0) FROM candidate JOIN frame "
                 "ON frame.id = candidate.frame_id JOIN flight ON flight.id = frame.flight_id WHERE campaign_id = ?",
                 (campaign_id,)).fetchone()
        measured = q("SELECT count(*) FROM heliostat WHERE campaign_id = ? AND canting_rms_mrad IS NOT NULL",
                     (campaign_id,)).fetchone()[0]
        return {
            "frames": {s: int(stages.get(s, 0)) for s in ("pending", "selected", "done", "skipped")},
            "frames_skipped_by_reason": frame_reasons,
            "pairs": {"candidates": int(cand[0]), "selected": int(cand[1]), "chosen": int(cand[2])},
            "pairs_skipped_by_reason": pair_reasons,
            "observations": {"done": int(obs.get("done", 0)), "failed": int(obs.get("failed", 0))},
            "heliostats_measured": int(measured),
        }

    def table_rows(self, table: str, campaign_id: int | None = None) -> tuple[list[str], list[tuple[Any, ...]]]:
        """Columns and rows of one export table (:data:`EXPORT_TABLES`)."""
        where = "" if campaign_id is None else " WHERE campaign.id = ?"
        args: tuple[Any, ...] = () if campaign_id is None else (campaign_id,)
        queries = {
            "campaigns": "SELECT campaign.* FROM campaign" + where,
            "flights": "SELECT campaign.name AS campaign, flight.* FROM flight JOIN campaign ON "
                       "campaign.id = flight.campaign_id" + where,
            "frames": "SELECT campaign.name AS campaign, flight.name AS flight, frame.id, frame.frame_key, "
                      "frame.file, frame.time_utc, frame.stage, frame.reason, frame.run_id, frame.seconds, frame.pose "
                      "FROM frame JOIN flight ON flight.id = frame.flight_id JOIN campaign ON "
                      "campaign.id = flight.campaign_id" + where,
            "candidates": "SELECT campaign.name AS campaign, flight.name AS flight, frame.frame_key, candidate.hua, "
                          "candidate.target, candidate.selected, candidate.chosen, candidate.reason, candidate.score, "
                          "candidate.metrics FROM candidate JOIN frame ON frame.id = candidate.frame_id JOIN flight "
                          "ON flight.id = frame.flight_id JOIN campaign ON campaign.id = flight.campaign_id" + where,
            "observations": "SELECT campaign.name AS campaign, flight.name AS flight, frame.frame_key, "
                            "observation.hua, observation.target, observation.status, observation.reason, "
                            "observation.seconds, observation.pihim_version, observation.parameters, "
                            "observation.result FROM observation JOIN frame ON frame.id = observation.frame_id "
                            "JOIN flight ON flight.id = frame.flight_id JOIN campaign ON "
                            "campaign.id = flight.campaign_id" + where,
            "heliostats": "SELECT campaign.name AS campaign, heliostat.name, heliostat.x_m, heliostat.y_m, "
                          "heliostat.z_m, heliostat.facets_used, heliostat.facets_total, heliostat.canting_rms_mrad, "
                          "heliostat.frames FROM heliostat JOIN campaign ON campaign.id = heliostat.campaign_id"
                          + where,
            "facets": "SELECT campaign.name AS campaign, heliostat.name AS heliostat, facet_result.facet, "
                      "facet_result.used, facet_result.reason, facet_result.az_mrad, facet_result.el_mrad, "
                      "facet_result.az_sigma_mrad, facet_result.el_sigma_mrad, facet_result.points, "
                      "facet_result.frame_ids, facet_result.pihim_version, facet_result.parameters, "
                      "facet_result.computed_utc FROM facet_result JOIN heliostat ON "
                      "heliostat.id = facet_result.heliostat_id JOIN campaign ON campaign.id = heliostat.campaign_id"
                      + where,
            "runs": "SELECT campaign.name AS campaign, run.* FROM run JOIN campaign ON campaign.id = run.campaign_id"
                    + where,
        }
        if table not in queries:
            raise PihimInputError(f"unknown table {table!r}; choose from {', '.join(EXPORT_TABLES)}")
        cur = self.db.execute(queries[table] + " ORDER BY 1, 2", args)
        cols = [d[0] for d in cur.description]
        return cols, [tuple(r) for r in cur.fetchall()]

    def export(self, out_dir: str | os.PathLike[str], *, fmt: str = "csv",
               campaign_id: int | None = None) -> dict[str, Path]:
        """Write every export table as ``OUT/<table>.csv`` (or ``.parquet``, needs pyarrow), atomically.

        Returns
        -------
        dict of Path
            Table name to file.
        """
        from pihim._atomic import atomic_group

        if fmt not in ("csv", "parquet"):
            raise PihimInputError(f"export format must be csv or parquet, got {fmt!r}")
        if fmt == "parquet":
            try:
                import pyarrow as pa
                import pyarrow.parquet as pq
            except ImportError:
                raise PihimInputError("Parquet export needs pyarrow: pip install 'pihim[parquet]'") from None
        out = Path(out_dir)
        data = {t: self.table_rows(t, campaign_id) for t in EXPORT_TABLES}
        paths = {t: out / f"{t}.{fmt}" for t in EXPORT_TABLES}
        with atomic_group(list(paths.values())) as tmps:
            for (table, (cols, rows)), tmp in zip(data.items(), tmps, strict=True):
                if fmt == "csv":
                    buf = io.StringIO()
                    w = csv.writer(buf, lineterminator="\n")
                    w.writerow(cols)
                    w.writerows(rows)
                    tmp.write_text(buf.getvalue(), encoding="utf-8")
                else:
                    columns = {c: [r[k] for r in rows] for k, c in enumerate(cols)}
                    pq.write_table(pa.table(columns), str(tmp))
        return paths


class _Transaction:
    """``BEGIN IMMEDIATE`` ... ``COMMIT`` (``ROLLBACK`` on any exception, including KeyboardInterrupt)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self.db = db

    def __enter__(self) -> None:
        for attempt in range(50):
            try:
                self.db.execute("BEGIN IMMEDIATE")
                return
            except sqlite3.OperationalError as exc:  # locked by another writer beyond the busy timeout
                if "locked" not in str(exc) or attempt == 49:
                    raise
                _time.sleep(0.1)

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.db.execute("COMMIT")
        else:
            self.db.execute("ROLLBACK")


def open_store(path: str | os.PathLike[str], *, create: bool = True, readonly: bool = False) -> CampaignStore:
    """Open (and migrate) a campaign store; ``create=False`` refuses a missing file.

    ``readonly=True`` (``pihim campaign report`` and ``export``) never writes
    the file: a missing, empty or empty-SQLite file is refused and an older
    schema is migrated in a temporary copy (:class:`CampaignStore`).

    Raises
    ------
    PihimInputError
        Not an SQLite file, an SQLite file of another application, a schema
        newer than this pihim's (the file is left untouched); read-only, also
        a missing, 0-byte or empty SQLite file.
    """
    return CampaignStore(path, create=create, readonly=readonly)
