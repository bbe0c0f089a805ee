"""``pihim simulate-flight`` and ``pihim campaign run|report|export``: campaigns at field scale.

Thin layers over :func:`pihim.campaign.flight.simulate_flight`,
:func:`pihim.campaign.run.run_campaign`, :func:`pihim.campaign.report.write_report`
and :meth:`pihim.campaign.store.CampaignStore.export`; see ``docs/campaign.md``
and ``docs/cli.md``. Heavy modules are imported inside the commands.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import typer

from pihim.cli._common import emit_json, stderr_console
from pihim.errors import PihimInputError

app = typer.Typer(name="campaign", help="Campaigns at field scale: run, report, export.", no_args_is_help=True,
                  add_completion=False, pretty_exceptions_enable=False)


@contextlib.contextmanager
def _bars(enabled: bool) -> Iterator[Any]:
    """A ``progress(stage, done, total)`` callback drawing one bar per stage on stderr, or None."""
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("{task.description:<8}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=stderr_console(), transient=False) as bar:
        tasks: dict[str, Any] = {}

        def update(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        yield update


def _field_spec(field: str, facets: Path | None) -> tuple[str, str | None]:
    from pihim.cli._common import field_csv_option, load_field_option

    p = field_csv_option(field, facets)
    if p is None:
        return ("nsttf-like", None)
    load_field_option(field, facets)  # one-line error now for a malformed field
    return (str(p.resolve()), None if facets is None else str(facets.resolve()))


def simulate_flight(
    plan: Annotated[Path, typer.Argument(help="plan.json written by pihim plan.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Flight directory to write (frames/, frames.csv, flight.json, truth/); a killed run's frames are reused.")],
    flight: Annotated[int, typer.Option("--flight", help="1-based flight of the plan.")] = 1,
    fps: Annotated[float | None, typer.Option("--fps", help="Record N frames per second along the scan passes.")] = None,
    captures_only: Annotated[bool, typer.Option("--captures-only", help="One frame per capture waypoint (default).")] = False,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Stop after N frames.")] = None,
    size: Annotated[str, typer.Option("--size", help="Frame size WxH (even); the Triton's field of view is kept.")] = "2448x2048",
    log: Annotated[str, typer.Option("--log", help="Pose log: csv (frames.csv columns), ulog (PX4) or dataflash (ArduPilot).")] = "csv",
    canting_sigma_mrad: Annotated[float, typer.Option("--canting-sigma-mrad", help="Facet canting error sigma, mrad.")] = 3.0,
    gps_sigma_m: Annotated[float, typer.Option("--gps-sigma-m", help="Constant logged-position offset sigma, m.")] = 0.0,
    attitude_sigma_deg: Annotated[float, typer.Option("--attitude-sigma-deg", help="Logged attitude noise sigma, deg.")] = 0.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of every random draw (>= 0).")] = 0,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Render the frames a flight of a plan would record, with its log and the truth beside it."""
    import math

    from pihim._inputs import check_regular_file
    from pihim.cli._common import check_out_dir
    from pihim.cli.simulate import parse_size

    if fps is not None and captures_only:
        raise PihimInputError("--fps and --captures-only exclude each other")
    if fps is not None and not (math.isfinite(fps) and 0 < fps <= 60):
        raise PihimInputError(f"--fps must be in (0, 60], got {fps}")
    if max_frames is not None and max_frames < 1:
        raise PihimInputError(f"--max-frames must be >= 1, got {max_frames}")
    if flight < 1:
        raise PihimInputError(f"--flight must be >= 1, got {flight}")
    if log not in ("csv", "ulog", "dataflash"):
        raise PihimInputError(f"--log must be csv, ulog or dataflash, got {log!r}")
    from pihim.campaign.flight import SIGMA_LIMITS

    for name, v, top in zip(("--canting-sigma-mrad", "--gps-sigma-m", "--attitude-sigma-deg"),
                            (canting_sigma_mrad, gps_sigma_m, attitude_sigma_deg), SIGMA_LIMITS.values(), strict=True):
        if not (math.isfinite(v) and 0 <= v <= top):
            raise PihimInputError(f"{name} must be a finite number in [0, {top:g}], got {v}")
    if seed < 0:
        raise PihimInputError(f"--seed must be >= 0, got {seed}")
    if plan.is_dir():
        raise PihimInputError(f"{plan}: a folder; give its plan.json ({plan / 'plan.json'})")
    if not plan.exists():
        raise PihimInputError(f"{plan}: no such plan file")
    check_regular_file(plan, "plan.json file")
    w, h = parse_size(size)
    if out.exists() and (out / "flight.json").exists():
        raise PihimInputError(f"--out {out}: already holds a flight (flight.json); choose a new directory")
    from pihim.campaign.flight import load_plan, simulate_flight as _simulate

    load_plan(plan, flight)  # a malformed plan is one line before --out is made
    check_out_dir(out)  # made by the run, and removed again if its first frame is refused

    with _bars(sys.stderr.isatty()) as bar:
        summary = _simulate(plan, out, flight=flight, fps=fps, max_frames=max_frames, size=(w, h), log=log,
                            canting_sigma_mrad=canting_sigma_mrad, gps_sigma_m=gps_sigma_m,
                            attitude_sigma_deg=attitude_sigma_deg, seed=seed,
                            progress=None if bar is None else (lambda d, t: bar("render", d, t)))
    if json_out:
        emit_json(summary)
    else:
        stderr_console().print(f"[bold]pihim simulate-flight[/bold]: wrote {summary['frames']} frames "
                               f"({w}x{h}, {summary['reused']} reused from an earlier run) to {out}, "
                               f"poses in {summary['log']}, truth in {out / 'truth'}",
                               highlight=False, soft_wrap=True)
    return 0


@app.command("run")
def run(
    flights: Annotated[list[Path], typer.Argument(help="Flight directories (flight.json, frames.csv, frames, log).", show_default=False)],
    store: Annotated[Path, typer.Option("--store", help="SQLite campaign store (created if missing).")],
    field: Annotated[str, typer.Option("--field", help="nsttf-like or an OpenCSP heliostat CSV.")] = "nsttf-like",
    facets: Annotated[Path | None, typer.Option("--facets", help="OpenCSP facet CSV (with --field CSV).")] = None,
    campaign: Annotated[str | None, typer.Option("--campaign", help="Campaign name (default FIELD-DATE of the first frame).")] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help="tcp://HOST:PORT of a running dask scheduler.")] = None,
    workers: Annotated[int | None, typer.Option("--workers", help="Local worker processes (default: CPU count; at most 4 x CPU count).")] = None,
    stages: Annotated[str, typer.Option("--stages", help="select (polar + selection only) or all.")] = "all",
    frames_per_pair: Annotated[int, typer.Option("--frames-per-pair", help="Frames kept per HUA-target pair for canting (1 to 1000000).")] = 3,
    min_dolp: Annotated[float, typer.Option("--min-dolp", help="Reflection DoLP criterion, in [0, 1) (paper: 0.2).")] = 0.2,
    skip_uncovered: Annotated[bool, typer.Option("--skip-uncovered", help="Record frames outside their log as skipped instead of refusing.")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the run summary as JSON on stdout.")] = False,
) -> int:
    """Run or resume a campaign: polar, frame selection, edges and canting on dask; results in the store.

    Frames that cannot be read are recorded as skipped (and tried again by the
    next run) while the others are processed; the run then ends with one line
    counting them and exit status 2 (1 if every such failure was an internal error).
    """
    import math

    from pihim.campaign.run import MAX_FRAMES_PER_PAIR, RunParameters, check_scheduler_address, check_workers, \
        run_campaign
    from pihim.campaign.selection import SelectionCriteria

    if not flights:
        raise PihimInputError("give at least one flight directory")
    if campaign is not None and not campaign.strip():
        raise PihimInputError("--campaign must be a name, got an empty one (leave it out for FIELD-DATE)")
    check_workers(workers)
    if scheduler is not None:
        check_scheduler_address(scheduler)
    if not 1 <= frames_per_pair <= MAX_FRAMES_PER_PAIR:
        raise PihimInputError(f"--frames-per-pair must be in [1, {MAX_FRAMES_PER_PAIR}], got {frames_per_pair}")
    if not (math.isfinite(min_dolp) and 0 <= min_dolp < 1):
        raise PihimInputError(f"--min-dolp must be in [0, 1) (a DoLP is at most 1), got {min_dolp}")
    spec = _field_spec(field, facets)
    params = RunParameters(frames_per_pair=frames_per_pair, criteria=SelectionCriteria(min_reflection_dolp=min_dolp),
                           stages=stages)
    if store.exists():
        from pihim.campaign.store import open_store

        open_store(store).close()  # a newer schema or a foreign file: refused before any work
    unreadable: list[tuple[str, str]] = []
    with _bars(sys.stderr.isatty()) as bar:
        summary = run_campaign(flights, store, field_spec=spec, campaign=campaign, scheduler=scheduler,
                               workers=workers, parameters=params, skip_uncovered=skip_uncovered, progress=bar,
                               on_unreadable=lambda frame, why, stage: unreadable.append((frame, why, stage)))
    if json_out:
        emit_json(summary)
    else:
        c = summary["counts"]
        stderr_console().print(
            f"[bold]pihim campaign run[/bold]: campaign {summary['campaign']} in {store}: frames "
            f"{c['frames']['done']} done, {c['frames']['selected']} selected, {c['frames']['skipped']} skipped, "
            f"{c['frames']['pending']} pending; pairs {c['pairs']['selected']}/{c['pairs']['candidates']} selected, "
            f"{c['pairs']['chosen']} chosen; observations {c['observations']['done']} done, "
            f"{c['observations']['failed']} failed; {c['heliostats_measured']} heliostats measured "
            f"({summary['seconds']:.1f} s)", highlight=False, soft_wrap=True)
        for reason, n in c["pairs_skipped_by_reason"].items():
            stderr_console().print(f"  pairs skipped: {n} x {reason}", highlight=False, soft_wrap=True)
    return _unreadable_status(unreadable, sum(f["frames"] for f in summary["flights"]), store)


def _unreadable_status(unreadable: list[tuple[str, str, str]], frames: int, store: Path) -> int:
    """Exit status of a run, after one stderr line counting the frames it could not read (if any).

    Parameters
    ----------
    unreadable : list of (str, str, str)
        ``(FLIGHT/FRAME_ID, reason, stage)`` of each frame the run could not read, ``stage`` ``"select"``
        (recorded as skipped, tried again by the next run) or ``"canting"`` (its pairs recorded as failed).
    frames : int
        Frames of the run's flights.
    store : Path

    Returns
    -------
    int
        2 when a frame was bad input (truncated, not a frame, ...), 1 when
        every failure was an internal error, 0 when there was none.
    """
    if not unreadable:
        return 0
    bad = [u for u in unreadable if not u[1].startswith("internal error")]
    frame, why, _ = (bad or unreadable)[0]
    n_sel = sum(stage == "select" for *_, stage in unreadable)
    n_cant = len(unreadable) - n_sel
    parts = []
    if n_sel:
        parts.append(f"{n_sel} at selection, recorded as skipped (a rerun tries {'them' if n_sel > 1 else 'it'} again)")
    if n_cant:
        parts.append(f"{n_cant} at canting, {'their' if n_cant > 1 else 'its'} pairs recorded as failed")
    print(f"pihim: error: {len(unreadable)} of {frames} frames could not be read ({'; '.join(parts)}); the other "
          f"frames' results are in {store}; first: {frame}: {why}", file=sys.stderr)
    return 2 if bad else 1


@app.command("report")
def report(
    store: Annotated[Path, typer.Argument(help="SQLite campaign store.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Output directory (index.html, heliostat pages, figures).")],
    campaign: Annotated[str | None, typer.Option("--campaign", help="Campaign to report (default the latest).")] = None,
    compare: Annotated[str | None, typer.Option("--compare", help="Earlier campaign of the same field to compare with (default the one before).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Write the static HTML field-health report of a campaign."""
    from pihim.campaign.report import write_report
    from pihim.campaign.store import open_store
    from pihim.cli._common import check_out_dir

    check_out_dir(out)
    with open_store(store, readonly=True) as st:  # never writes the store (nor makes one of another file)
        summary = write_report(st, out, campaign=campaign, compare=compare)
    if json_out:
        emit_json(summary)
    else:
        stderr_console().print(f"[bold]pihim campaign report[/bold]: wrote {summary['files']['index']} "
                               f"({summary['heliostats_measured']} heliostats measured, "
                               f"{len(summary['files']) - 1} more files)", highlight=False, soft_wrap=True)
    return 0


@app.command("export")
def export(
    store: Annotated[Path, typer.Argument(help="SQLite campaign store.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Output directory (one file per table).")],
    fmt: Annotated[str, typer.Option("--format", help="csv or parquet (needs pyarrow).")] = "csv",
    campaign: Annotated[str | None, typer.Option("--campaign", help="Only this campaign (default all).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Export the store's tables to CSV or Parquet."""
    from pihim.campaign.store import open_store
    from pihim.cli._common import output_dir

    if fmt not in ("csv", "parquet"):
        raise PihimInputError(f"--format must be csv or parquet, got {fmt!r}")
    with open_store(store, readonly=True) as st:  # never writes the store (nor makes one of another file)
        cid = None
        if campaign is not None:
            rows = [r for r in st.campaigns() if r["name"] == campaign]
            if not rows:
                raise PihimInputError(f"{store}: no campaign {campaign!r}")
            cid = int(rows[0]["id"])
        with output_dir(out):  # e.g. Parquet without pyarrow: no empty --out left behind
            paths = st.export(out, fmt=fmt, campaign_id=cid)
        rows_per = {t: len(st.table_rows(t, cid)[1]) for t in paths}
    if json_out:
        emit_json({"schema": "pihim.campaign-export/1", "store": str(store), "format": fmt,
                   "files": {k: str(v) for k, v in paths.items()}, "rows": rows_per})
    else:
        stderr_console().print(f"[bold]pihim campaign export[/bold]: wrote {len(paths)} {fmt} files to {out}",
                               highlight=False, soft_wrap=True)
    return 0
