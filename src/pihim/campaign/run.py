"""A campaign run on dask.distributed: selection, canting, combination; resumable and idempotent.

:func:`run_campaign` takes flight directories (:mod:`pihim.campaign.flight`),
the field, and a store (:mod:`pihim.campaign.store`), and

1. **checks everything before anything is written**: every flight loads, its
   log covers every frame (else one error naming the first uncovered frame,
   unless ``skip_uncovered``), every frame file exists with the camera's
   size; the scheduler answers;
2. **registers** the campaign, its heliostats, flights and frames (existing
   rows are kept: a rerun registers nothing twice);
3. **selection** (stage ``select``): every frame still ``pending`` (or
   skipped as unreadable by an earlier run) is read on a worker, polar image
   and pair selection (:func:`pihim.campaign.selection.select_pairs`), and
   its candidates are written in one transaction; a frame that cannot be read
   is recorded as skipped (``unreadable: reason``) and the others go on;
4. **choice**: the best ``frames_per_pair`` frames of each selected pair
   (highest reflection DoLP);
5. **canting** (stage ``canting``): each frame with chosen pairs that have no
   observation yet is read once on a worker and
   :func:`pihim.inspection.pipeline.inspect_frame` runs for each of its pairs;
   the observations (or failures, with the one-line reason) are written in one
   transaction per frame;
6. **combination**: per heliostat, every observation combined
   (:func:`pihim.inspection.pipeline.combine_results`) and written per facet
   with its provenance.

The client process alone writes the store; workers get file paths and small
dictionaries and return small dictionaries, and at most ``2 x threads`` tasks
are in flight, so memory stays bounded by a few frames per worker whatever
the flight's length. A run killed at any point (``kill -9``) and started
again finishes the work without redoing finished frames and without
duplicating a row (each unit of work is one transaction; rows are unique).

Workers of an existing cluster (``scheduler``) must see the flight
directories and the field files at the same paths.
"""

from __future__ import annotations

import hashlib
import os
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field as _dc_field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from pihim.campaign.selection import SelectionCriteria
from pihim.errors import PihimInputError

__all__ = ["MAX_FRAMES_PER_PAIR", "RUN_SCHEMA_ID", "SCHEDULER_SCHEMES", "STAGES", "WORKERS_PER_CPU", "RunParameters",
           "check_scheduler_address", "check_workers", "connect", "max_local_workers", "run_campaign"]

RUN_SCHEMA_ID = "pihim.campaign-run/1"
#: ``select``: selection only; ``all``: selection, canting and combination.
STAGES = ("select", "all")
#: Largest ``frames_per_pair``: more than the frames of any campaign (a 20-minute flight at 15 fps has 18,000).
MAX_FRAMES_PER_PAIR = 1_000_000
#: Network schemes of dask.distributed's comms a scheduler address may use (``inproc://`` also, from Python).
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")
#: A LocalCluster has at most this many worker processes per CPU (see :func:`max_local_workers`).
WORKERS_PER_CPU = 4

Progress = Callable[[str, int, int], Any]


@dataclass(frozen=True)
class RunParameters:
    """Parameters of a run (stored with every result as provenance).

    Attributes
    ----------
    frames_per_pair : int
        Frames kept per HUA-target pair for the canting estimate.
    criteria : SelectionCriteria
    stages : {"select", "all"}
    """

    frames_per_pair: int = 3
    criteria: SelectionCriteria = _dc_field(default_factory=SelectionCriteria)
    stages: str = "all"

    def __post_init__(self) -> None:
        if isinstance(self.frames_per_pair, bool) or not isinstance(self.frames_per_pair, int) \
                or not 1 <= self.frames_per_pair <= MAX_FRAMES_PER_PAIR:
            raise PihimInputError(f"frames per pair must be an integer in [1, {MAX_FRAMES_PER_PAIR}], "
                                  f"got {self.frames_per_pair!r}")
        if self.stages not in STAGES:
            raise PihimInputError(f"stages must be one of {', '.join(STAGES)}, got {self.stages!r}")

    def as_dict(self) -> dict[str, Any]:
        return {"frames_per_pair": self.frames_per_pair, "criteria": asdict(self.criteria), "stages": self.stages,
                "demosaic": "full"}


# --------------------------------------------------------------------------- worker side


@lru_cache(maxsize=4)
def _field(spec: tuple[str, str | None]) -> Any:
    """The field on a worker, loaded once per process (``("nsttf-like", None)`` or ``(csv, facets)``)."""
    from pihim.field import NSTTF_TOWER, load_field, nsttf_like_field

    src, facets = spec
    if src == "nsttf-like":
        return nsttf_like_field()
    return load_field(Path(src), None if facets is None else Path(facets), tower=NSTTF_TOWER)


_POSE_CACHE: dict[str, Any] = {}


def _field_pose(fld: Any, log: Mapping[str, Any]) -> Any:
    """The field tracked at the frame's time rounded to the second, cached per worker process.

    The sun moves 0.07 mrad per second, the tracking normals half that: far
    below what the selection looks at; one tracking serves 15 frames at 15 fps.
    """
    import json
    from datetime import datetime, timezone

    from pihim.inspection.pipeline import field_pose_from_log

    t = datetime.fromisoformat(str(log["time"]).replace("Z", "+00:00")).timestamp()
    when = datetime.fromtimestamp(round(t), tz=timezone.utc).isoformat()
    key = json.dumps([id(fld), when, log.get("site"), log.get("aim_point_m"), log.get("heliostats")],
                     sort_keys=True, default=str)
    pose = _POSE_CACHE.get(key)
    if pose is None:
        if len(_POSE_CACHE) > 64:
            _POSE_CACHE.clear()
        pose = field_pose_from_log(fld, {**log, "time": when})
        _POSE_CACHE[key] = pose
    return pose


def _read_raw(path: str) -> np.ndarray:
    from pihim.camera.frames import read_frame

    return np.asarray(read_frame(path).data)


def select_task(path: str, log: Mapping[str, Any], field_spec: tuple[str, str | None],
                criteria: Mapping[str, float]) -> dict[str, Any]:
    """Worker task: read one frame and select its pairs (a failure is returned, not raised)."""
    from pihim.campaign.selection import select_pairs

    t0 = _time.perf_counter()
    try:
        raw = _read_raw(path)
        fld = _field(field_spec)
        out = select_pairs(raw, log, fld, SelectionCriteria(**criteria), field_pose=_field_pose(fld, log))
        out["error"] = None
    except PihimInputError as exc:
        out = {"candidates": [], "error": " ".join(str(exc).split())}
    except Exception as exc:  # noqa: BLE001 - one frame's internal error must not stop a campaign; it is counted
        out = {"candidates": [], "error": f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())}"}
    out["seconds_total"] = _time.perf_counter() - t0
    return out


def _result_dict(res: Any) -> dict[str, Any]:
    d = res.canting.to_dict()
    return {"canting": d, "image": res.image, "pose": res.pose, "seconds": res.seconds}


def _default_inspector(raw: np.ndarray, log: Mapping[str, Any], field: Any, hua: str, target: str) -> Any:
    from pihim.inspection.pipeline import inspect_frame

    return inspect_frame(raw, log, field, hua=hua, target=target)


def inspect_task(path: str, log: Mapping[str, Any], field_spec: tuple[str, str | None],
                 pairs: Sequence[tuple[str, str]], inspector: Callable[..., Any] | None = None) -> list[dict[str, Any]]:
    """Worker task: read one frame once and estimate the canting of each of its chosen pairs.

    A frame that cannot be read fails every pair with the reason and
    ``"unreadable": True``; a pair whose inspection fails is failed with its reason.
    """
    fn = inspector or _default_inspector
    out: list[dict[str, Any]] = []
    try:
        raw = _read_raw(path)
    except Exception as exc:  # noqa: BLE001 - an unreadable frame is recorded and counted, the campaign goes on
        why = " ".join(str(exc).split())
        why = why if isinstance(exc, PihimInputError) else f"internal error: {type(exc).__name__}: {why}"
        return [{"hua": h, "target": t, "status": "failed", "reason": why, "seconds": 0.0, "unreadable": True}
                for h, t in pairs]
    fld = _field(field_spec)
    for hua, target in pairs:
        t0 = _time.perf_counter()
        try:
            res = fn(raw, log, fld, hua, target)
            out.append({"hua": hua, "target": target, "status": "done", "result": _result_dict(res),
                        "seconds": _time.perf_counter() - t0})
        except PihimInputError as exc:
            out.append({"hua": hua, "target": target, "status": "failed", "reason": " ".join(str(exc).split()),
                        "seconds": _time.perf_counter() - t0})
        except Exception as exc:  # noqa: BLE001 - one frame's internal error must not stop a campaign
            out.append({"hua": hua, "target": target, "status": "failed",
                        "reason": f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())}",
                        "seconds": _time.perf_counter() - t0})
    return out


# --------------------------------------------------------------------------- client side


def _silence_dask_logs() -> dict[str, int]:
    """Set the ``distributed`` and ``tornado`` loggers (and their children already made) to CRITICAL.

    Returns the levels they had (``logging.Logger.level``), to put back.
    """
    import logging

    names = [n for n in logging.root.manager.loggerDict if n.startswith(("distributed.", "tornado."))]
    before = {}
    for name in ("distributed", "tornado", *names):
        logger = logging.getLogger(name)
        before[name] = logger.level
        logger.setLevel(logging.CRITICAL)
    return before


def _quiet_interrupt() -> Callable[[], None]:
    """Make Ctrl-C stop the run with KeyboardInterrupt, without dask's shutdown tracebacks; returns the undo.

    An interrupt cancels the client's pending calls, and distributed and
    tornado log the cancellations (tracebacks, at ERROR) while the cluster
    closes. While the run is on, SIGINT raises their loggers to CRITICAL
    before raising KeyboardInterrupt, so the command's own line (exit 130)
    is all that is said. Only in the main thread, and only over Python's
    default handler or the command line's (:class:`pihim._interrupts.Interrupts`,
    which then decides: a press repeated at once is absorbed); the returned
    function (called once the cluster is closed) puts that handler and the
    loggers' levels back.
    """
    import logging
    import signal
    import threading

    from pihim._interrupts import Interrupts

    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() \
            or not (previous is signal.default_int_handler or isinstance(previous, Interrupts)):
        return lambda: None
    silenced: dict[str, int] = {}

    def interrupt(signum: int, frame: Any) -> None:
        silenced.update({k: v for k, v in _silence_dask_logs().items() if k not in silenced})
        previous(signum, frame)  # type: ignore[operator]

    if hasattr(previous, "held_back"):  # presses held back by pihim._forked.signals_deferred, told to it
        interrupt.held_back = previous.held_back  # type: ignore[attr-defined]

    def undo() -> None:
        signal.signal(signal.SIGINT, previous)
        for name, level in silenced.items():
            logging.getLogger(name).setLevel(level)

    signal.signal(signal.SIGINT, interrupt)
    return undo


def dask_setup(worker: Any) -> None:
    """Worker preload of the local cluster (``preload=["pihim.campaign.run"]``): ignore SIGINT, log nothing.

    Ctrl-C at a terminal reaches every process of the foreground group, the
    worker processes too; the client alone handles it (it stops the run and
    closes the cluster, exit 130), so a worker must not die of it on its own
    with a traceback. Nor may a worker print the lost heartbeat of a
    scheduler closing before it: the worker's dask logging is at CRITICAL
    (a frame's failure is recorded by the client; a dead worker fails the
    run there). Called by dask in the worker's main thread. tifffile's own
    log lines about a corrupt file are silenced as in the command line's
    process: the frame's failure names the file in one line.
    """
    import logging
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _silence_dask_logs()
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)


def max_local_workers() -> int:
    """The most worker processes a LocalCluster may have: :data:`WORKERS_PER_CPU` x the CPU count.

    Each worker is a process with one thread (about 150 MB before it reads a
    frame); beyond the cores more workers only share them, and an absurd
    count would exhaust the memory before a frame is read.
    """
    return WORKERS_PER_CPU * (os.cpu_count() or 1)


def check_workers(workers: int | None) -> None:
    """Refuse a LocalCluster size outside ``[1, max_local_workers()]`` (None: the CPU count) in one line.

    Raises
    ------
    PihimInputError
        Not an integer, < 1, or more than :func:`max_local_workers`.
    """
    if workers is None:
        return
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise PihimInputError(f"--workers must be an integer >= 1, got {workers!r}")
    top = max_local_workers()
    if workers > top:
        raise PihimInputError(f"--workers {workers}: at most {top} local workers ({WORKERS_PER_CPU} x the "
                              f"{os.cpu_count() or 1} CPUs of this machine); use --scheduler for a larger cluster")


def check_scheduler_address(address: str) -> str:
    """``address`` as ``tcp://HOST:PORT`` (a bare ``HOST:PORT`` is TCP), or a one-line :class:`PihimInputError`.

    Checked before any connection is tried, so a malformed address costs no
    time and leaves no half-made client behind.

    Parameters
    ----------
    address : str
        ``tcp://HOST:PORT`` (or ``tls``, ``ws``, ``wss``, ``ucx``) or ``HOST:PORT``; an IPv6
        host in brackets (``tcp://[::1]:8786``); ``inproc://...`` of a
        scheduler in this process.

    Returns
    -------
    str
        The address with its scheme.
    """
    text = address.strip()
    scheme, sep, loc = text.rpartition("://")
    scheme = scheme.lower() if sep else "tcp"
    if scheme == "inproc" and loc and not any(c.isspace() for c in loc):
        return text  # a scheduler in this process (LocalCluster(processes=False)), from Python only
    host, colon, port = loc.rpartition(":")
    bracketed = host.startswith("[") and host.endswith("]")
    bare = host[1:-1] if bracketed else host
    ok = (scheme in SCHEDULER_SCHEMES and bool(colon) and port.isascii() and port.isdigit()
          and 1 <= int(port) <= 65535 and bool(bare) and not any(c.isspace() or c in "/?#@[]" for c in bare)
          and (bracketed or ":" not in bare))  # an IPv6 host needs its brackets
    if not ok:
        raise PihimInputError(f"--scheduler {address!r}: not a dask scheduler address tcp://HOST:PORT "
                              f"(or {', '.join(s + '://' for s in SCHEDULER_SCHEMES[1:])}; port 1-65535)")
    return f"{scheme}://{loc}"


def connect(scheduler: str | None, workers: int | None, *, processes: bool = True,
            timeout_s: float = 5.0) -> tuple[Any, Any]:
    """A dask.distributed client: to ``scheduler`` (``tcp://HOST:PORT``) or to a new LocalCluster.

    Returns ``(client, cluster)``; ``cluster`` is None for an existing
    scheduler. A malformed address (:func:`check_scheduler_address`), one
    that does not answer within ``timeout_s``, or more local ``workers`` than
    :func:`max_local_workers` is a one-line :class:`PihimInputError`.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise PihimInputError("campaign runs need dask.distributed: pip install 'pihim[campaign]'") from None
    import logging

    for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.worker", "tornado"):
        logging.getLogger(name).setLevel(logging.ERROR)
    if scheduler is not None:
        if workers is not None:
            raise PihimInputError("--workers applies to the local cluster; an existing cluster has its own workers")
        address = check_scheduler_address(scheduler)
        try:
            client = Client(address, timeout=f"{timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise PihimInputError(f"--scheduler {scheduler}: no dask scheduler answers "
                                  f"({' '.join(str(exc).split())[:160]})") from None
        return client, None
    check_workers(workers)
    n = workers if workers is not None else (os.cpu_count() or 1)
    # the scheduler's HTTP server on a free port (":0": 8787 may be taken); one thread per worker: parallelism
    # comes from the workers; numba's and OpenCV's own thread pools would
    # oversubscribe the cores (set before the worker processes import them)
    env = {k: "1" for k in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    kwargs: dict[str, Any] = {"env": env, "preload": ["pihim.campaign.run"]} if processes else {}
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes, dashboard_address=":0",
                           silence_logs=logging.ERROR, **kwargs)
    return Client(cluster, set_as_default=False), cluster


def field_key(field: Any) -> str:
    """A digest of the field's heliostat names and pivots (campaigns of the same field share it)."""
    h = hashlib.sha1()
    for n in field.names:
        h.update(n.encode())
    h.update(np.round(np.asarray(field.pivots, float), 3).tobytes())
    return h.hexdigest()[:16]


def _map_bounded(client: Any, fn: Callable[..., Any], jobs: Sequence[tuple[Any, tuple[Any, ...]]],
                 in_flight: int, on_result: Callable[[Any, Any], None]) -> None:
    """Submit ``fn(*args)`` for each ``(key, args)``, at most ``in_flight`` at a time; results as they finish."""
    from distributed import as_completed

    it = iter(jobs)
    futures = {}
    for key, args in it:
        futures[client.submit(fn, *args, pure=False)] = key
        if len(futures) >= in_flight:
            break
    ac = as_completed(list(futures), loop=client.loop)
    for fut in ac:
        key = futures.pop(fut)
        result = fut.result()
        fut.release()
        on_result(key, result)
        nxt = next(it, None)
        if nxt is not None:
            f2 = client.submit(fn, *nxt[1], pure=False)
            futures[f2] = nxt[0]
            ac.add(f2)


def _canting_from_dict(d: Mapping[str, Any]) -> Any:
    from pihim.inspection.canting import CantingResult, FacetCanting

    facets = tuple(FacetCanting(**{k: f.get(k) for k in FacetCanting.__dataclass_fields__ if k in f})
                   for f in d["facets"])
    o = d.get("orientation_mrad") or {}
    return CantingResult(d["hua"], d["target"], facets, o.get("az"), o.get("el"), int(d.get("frames", 1)),
                         tuple(d.get("notes", ())))


def canting_rms_mrad(facets: Sequence[Mapping[str, Any]]) -> float | None:
    """RMS of the used facets' deviations over both axes, mrad: ``sqrt(mean(az^2 + el^2) / 2)``.

    None with fewer than two used facets: deviations are relative to the used
    facets' mean, so one facet is its own reference (always 0).
    """
    v = [(f["az_mrad"], f["el_mrad"]) for f in facets if f.get("used") and f.get("az_mrad") is not None]
    if len(v) < 2:
        return None
    a = np.asarray(v, float)
    return float(np.sqrt(np.mean(a**2)))


def combine_campaign(store: Any, campaign_id: int, parameters: Mapping[str, Any],
                     huas: Sequence[str] | None = None) -> int:
    """Combine every heliostat's observations and write the facet results; returns heliostats written."""
    import json

    from pihim.inspection.pipeline import combine_results

    by_hua = store.observations_by_hua(campaign_id)
    n = 0
    for hua, rows in sorted(by_hua.items()):
        if huas is not None and hua not in huas:
            continue
        results = [_canting_from_dict(json.loads(r["result"])["canting"]) for r in rows]
        comb = combine_results(results)
        facets = [f.to_dict() for f in comb.facets]
        store.record_heliostat(campaign_id, hua, facets,
                               frame_ids=[f"{r['flight_name']}/{r['frame_key']}" for r in rows],
                               parameters=parameters, rms_mrad=canting_rms_mrad(facets), frames=len(rows))
        n += 1
    return n


def run_campaign(flight_dirs: Sequence[str | os.PathLike[str]], store_path: str | os.PathLike[str], *,
                 field_spec: tuple[str, str | None] = ("nsttf-like", None), campaign: str | None = None,
                 scheduler: str | None = None, workers: int | None = None,
                 parameters: RunParameters = RunParameters(), skip_uncovered: bool = False,
                 processes: bool = True, inspector: Callable[..., Any] | None = None,
                 progress: Progress | None = None,
                 on_unreadable: Callable[[str, str], Any] | None = None) -> dict[str, Any]:
    """Run (or resume) a campaign; see the module notes.

    Parameters
    ----------
    flight_dirs : sequence of path-like
    store_path : path-like
        The SQLite store (created if missing).
    field_spec : (str, str or None)
        ``("nsttf-like", None)`` or ``(HELIOSTATS.csv, FACETS.csv or None)``.
    campaign : str, optional
        Campaign name; default ``<field>-<date of the first frame>``.
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running dask scheduler; default a LocalCluster.
    workers : int, optional
        LocalCluster worker processes (default the CPU count).
    parameters : RunParameters
    skip_uncovered : bool
        Record frames outside their log as skipped instead of refusing the run.
    processes : bool
        LocalCluster workers as processes (True) or threads of this process.
    inspector : callable, optional
        ``inspector(raw, log, field, hua, target) -> InspectionResult``;
        default :func:`pihim.inspection.pipeline.inspect_frame`.
    progress : callable, optional
        ``progress(stage, done, total)``.
    on_unreadable : callable, optional
        ``on_unreadable(frame, reason, stage)`` for each frame of this run that
        could not be read, ``frame`` as ``FLIGHT/FRAME_ID``; the reason is one
        line, ``internal error: ...`` for a failure that is not the frame's
        fault. At ``stage`` ``"select"`` (or when its selection failed) the
        frame is recorded as skipped (``unreadable: reason``) and the next run
        tries it again; at ``"canting"`` (a frame read at selection that could
        not be read again) its pairs are recorded as failed observations, not
        tried again. The run goes on either way.

    Returns
    -------
    dict
        The ``pihim.campaign-run/1`` summary.
    """
    from pihim.campaign.flight import check_frame_files, frame_log, load_flight
    from pihim.campaign.logs import format_utc
    from pihim.campaign.store import open_store
    from pihim.inspection.pipeline import logged_aim_and_drives

    t_start = _time.perf_counter()
    if not flight_dirs:
        raise PihimInputError("give at least one flight directory")
    # 1. check everything first
    fld = _field(field_spec)
    flights = []
    names: set[str] = set()
    for d in flight_dirs:
        fl = load_flight(d)
        if fl.name in names:
            raise PihimInputError(f"two flights are named {fl.name!r}; flight names must differ (flight.json name)")
        names.add(fl.name)
        bad = fl.uncovered
        if bad and not skip_uncovered:
            raise PihimInputError(
                f"{fl.directory}: {len(bad)} of {len(fl.matches)} frames are not covered by the log "
                f"(first: frame {bad[0].frame.frame_id}: {bad[0].reason}); fix the log or pass --skip-uncovered")
        if len(bad) == len(fl.matches):
            raise PihimInputError(f"{fl.directory}: the log covers none of the frames")
        check_frame_files(fl)
        covered = next(m for m in fl.matches if m.ok)
        try:  # the log's aim point and drive angles are the flight's: refused once, not frame by frame
            logged_aim_and_drives(fld, frame_log(fl, covered))
        except PihimInputError as exc:
            raise PihimInputError(f"{fl.directory}: {exc}") from None
        flights.append(fl)
    client = cluster = store = None
    restore_sigint = _quiet_interrupt()
    try:
        client, cluster = connect(scheduler, workers, processes=processes)  # before the store is touched
        store = open_store(store_path)
        nthreads = max(1, sum(client.nthreads().values()))
        # 2. register
        first = min(m.frame.time_utc_s for fl in flights for m in fl.matches)
        name = campaign or f"{'nsttf-like' if field_spec[0] == 'nsttf-like' else Path(field_spec[0]).stem}-" \
                           f"{format_utc(first)[:10]}"
        pivots = np.asarray(fld.pivots, float)
        cid = store.ensure_campaign(name, field_source=str(field_spec[0]), field_key=field_key(fld),
                                    heliostats=[(n, *pivots[i]) for i, n in enumerate(fld.names)])
        by_flight: dict[str, Any] = {}
        for fl in flights:
            rows = []
            for m in fl.matches:
                pose = None if m.pose is None else _json(m.pose.to_dict())
                rows.append((m.frame.frame_id, m.frame.file, format_utc(m.frame.time_utc_s), pose,
                             None if m.ok else f"outside the log: {m.reason}"))
            store.ensure_flight(cid, fl.name, str(fl.directory.resolve()), fl.log_kind, rows)
            by_flight[fl.name] = fl
        params = parameters.as_dict()
        run_id = store.start_run(cid, {**params, "flights": [str(f.directory) for f in flights],
                                       "scheduler": scheduler or f"LocalCluster({nthreads})"})
        matches = {(fl.name, m.frame.frame_id): m for fl in flights for m in fl.matches}
        processed = 0

        # 3. selection
        pending = store.pending_frames(cid)
        jobs = []
        frame_names: dict[int, str] = {}
        for row in pending:
            fl = by_flight.get(row["flight_name"])
            if fl is None:
                continue  # a flight of an earlier run not given this time: left pending
            m = matches[(fl.name, row["frame_key"])]
            frame_names[row["id"]] = f"{fl.name}/{row['frame_key']}"
            jobs.append((row["id"], (str(fl.frame_path(m.frame)), frame_log(fl, m), field_spec,
                                     asdict(parameters.criteria))))
        done_sel = 0

        def on_selected(frame_id: int, res: dict[str, Any]) -> None:
            nonlocal done_sel, processed
            store.record_selection(frame_id, res["candidates"], run_id=run_id, seconds=res["seconds_total"],
                                   skip_reason=None if res["error"] is None else f"unreadable: {res['error']}")
            if res["error"] is not None and on_unreadable is not None:
                on_unreadable(frame_names[frame_id], res["error"], "select")
            done_sel += 1
            processed += 1
            if progress:
                progress("select", done_sel, len(jobs))

        if progress:
            progress("select", 0, len(jobs))
        _map_bounded(client, select_task, jobs, 2 * nthreads, on_selected)

        observed = 0
        combined = 0
        if parameters.stages == "all":
            # 4. choice, 5. canting
            store.choose(cid, parameters.frames_per_pair)
            todo = store.frames_to_inspect(cid)
            jobs = []
            for row, pairs in todo:
                fl = by_flight.get(row["flight_name"])
                if fl is None:
                    continue
                m = matches[(fl.name, row["frame_key"])]
                frame_names[row["id"]] = f"{fl.name}/{row['frame_key']}"
                jobs.append((row["id"], (str(fl.frame_path(m.frame)), frame_log(fl, m), field_spec, pairs,
                                         inspector)))
            done_insp = 0

            def on_inspected(frame_id: int, obs: list[dict[str, Any]]) -> None:
                nonlocal done_insp, observed, processed
                store.record_observations(frame_id, obs, run_id=run_id, parameters=params)
                if obs and obs[0].get("unreadable") and on_unreadable is not None:
                    on_unreadable(frame_names[frame_id], obs[0]["reason"], "canting")
                done_insp += 1
                observed += len(obs)
                processed += 1
                if progress:
                    progress("canting", done_insp, len(jobs))

            if progress:
                progress("canting", 0, len(jobs))
            _map_bounded(client, inspect_task, jobs, 2 * nthreads, on_inspected)
            # 6. combination
            combined = combine_campaign(store, cid, params)
        store.finish_run(run_id, processed)
        counts = store.counts(cid)
    finally:
        try:
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
            if store is not None:
                store.close()
        finally:
            restore_sigint()
    return {
        "schema": RUN_SCHEMA_ID,
        "store": str(store_path),
        "campaign": name,
        "run_id": run_id,
        "flights": [{"name": fl.name, "frames": len(fl.matches), "log": fl.log_kind,
                     "uncovered": len(fl.uncovered)} for fl in flights],
        "stages": parameters.stages,
        "workers": nthreads,
        "scheduler": scheduler,
        "processed_this_run": {"frames_selected": done_sel, "observations": observed,
                               "heliostats_combined": combined},
        "counts": counts,
        "parameters": params,
        "seconds": round(_time.perf_counter() - t_start, 3),
    }


def _json(obj: Any) -> str:
    import json

    return json.dumps(obj, sort_keys=True, allow_nan=False, separators=(",", ":"))

