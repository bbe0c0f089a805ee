"""Day sweep: when in the day can the field be inspected with usable polarimetric contrast?

:func:`sweep_day` samples one day at a site (default NSTTF, local time
America/Denver) every ``step_min`` minutes while the sun is above
``min_elevation_deg`` (default 10 deg). At each time it tracks the field
(once, shared by the planner and the scoring), plans the UFACET passes
(:func:`pihim.planning.ufacet.plan_passes`), scores every planned image and
applies contrast-raising shifts (:func:`pihim.planning.scoring.score_passes`),
and records the fraction of the field's heliostats that have at least one
usable image (:func:`pihim.planning.scoring.coverage`):

``fraction_sky``
    an image with the sky-vs-sky DoLP difference > 0.2 and the HUA
    reflection DoLP > 0.2;
``fraction_ground``
    an image with the ground-vs-ground AoP difference > 50 deg and the HUA
    reflection DoLP > 0.2;
``fraction_either``
    an image usable by either scenario (the paper's processing criterion);
``fraction_planned``
    an image at all (UFACET geometry only).

The denominator is every heliostat of the field (heliostats the planner
cannot assess count as not coverable). :meth:`DaySweep.windows` finds the
contiguous runs of samples at or above a threshold.

Does the sweep agree with the paper's favourable windows?
---------------------------------------------------------
The paper (sec. 4.1) reports 9:30-11:30 and 14:00-16:00 local time as
favourable at the NSTTF. Defaults used here: NSTTF-like field tracking the
tower target (the field in operation), UFACET passes at 15-25 m
(:mod:`pihim.planning.ufacet`), Rayleigh sky with a maximum DoLP of 0.8 and
100 W m^-2 diffuse irradiance, second-surface mirrors, Torrance-Sparrow
ground (sigma 15 deg, n = 1.45, sun 1000 W m^-2), default shift search.
``fraction_either`` (MDT, UTC-6):

=============  ============================  ==========================  =========================
date           minimum                       morning peak                afternoon peak
=============  ============================  ==========================  =========================
2021-05-13     0.00 at 12:50 (noon 13:00,    0.76 at 09:20               0.76 at 17:00
               sun 74 deg high)
2021-03-20     0.01 at 13:00 (noon 13:10,    0.49 at 10:20               0.50 at 16:20
               sun 55 deg high)
=============  ============================  ==========================  =========================

Windows at 0.8 of the day's best (``relative=True``): 08:20-10:20 and
15:50-17:50 on 2021-05-13; 09:10-11:00 and 15:30-17:10 on 2021-03-20. At an
absolute 0.3: 07:50-11:20 and 14:50-18:20; 09:00-11:30 and 15:00-17:30.

**Verdict: the sweep agrees on the structure, and at the equinox on the
morning window, but puts the afternoon window about one hour later** than
the paper's. Two windows placed nearly symmetrically about solar noon are
separated by a deep minimum at noon, where essentially no heliostat is
usable. At the equinox the predicted morning window (09:10-11:00, peak
10:20) matches the paper's 9:30-11:30; the afternoon one (15:30-17:10, peak
16:20) starts where the paper's 14:00-16:00 ends. In May the windows sit
further from noon (peaks 09:20 and 17:00) and the paper's windows are
about half covered. Why:

* **The contrast comes from the ground-vs-ground edge.** With every
  heliostat tracking, neighbouring mirrors differ in orientation by a few
  degrees, so the skies they reflect toward the camera differ by a few
  degrees; with the sky's DoLP gradient of at most ~0.015 per degree the
  predicted sky-vs-sky DoLP differences stay below ~0.04 at the five
  instants examined below (07:00-18:50), ``fraction_sky`` is 0 on both dates (with one neighbour turned face up,
  as in the paper's sky-vs-sky test, differences above 0.3 appear; see
  ``tests/planning/test_scoring.py``). The paper measured its sky-vs-sky
  contrast with all heliostats but the pair facing up, which does not carry
  over to a field in operation. The windows are set by the AoP difference
  between the mirror-reflected ground at the HUA's lower edge and the real
  ground beside it.
* **Noon is unusable because the geometry becomes coplanar.** The AoP
  difference is governed by how far the sun lies out of the plane of
  incidence at the lower edge (the plane through the camera's line of
  sight and the mirror normal): across the NSTTF images on 2021-05-13 their
  correlation is 0.91-0.98 from mid-morning to mid-afternoon (0.49-0.57 at
  low sun, where the reflection DoLP limits instead). Near solar noon the
  sun is high and due South, the heliostats North of the tower face South,
  and the UFACET cameras look
  along the heliostats' North-South vertical planes, so the sun lies within
  ~5 deg (median) of that plane: the sunlit microfacets that send light to
  the camera and to the mirror then polarize it in (nearly) the same plane,
  the mirror reflection keeps that orientation, and both regions show the
  same AoP (median difference 15 deg). The noon sun being "too high" is
  the same statement: it stays close to the North-South planes for longer
  in summer, which is why the May minimum is wider.
* **Mid-morning and mid-afternoon are good** because the sun is then
  33-36 deg (median) out of those planes (09:20 and 17:00 on 2021-05-13):
  median AoP differences of 72-73 deg, above the paper's 50 deg on 84-85 %
  of the images, and the mirror-reflected ground carries a DoLP of about
  0.46-0.47 (median), well above the paper's 0.2 gate.
* **Early morning and late afternoon drop off** although the sun is even
  further out of plane (~43 deg): with the sun low, the light the ground
  sends toward the mirrors is less polarized (median DoLP of the
  mirror-reflected ground 0.16 at 07:00, 0.21 at 18:50), 67 % and 44 % of
  the images fail the 0.2 reflection gate, and the AoP difference falls
  back to a median of 46-50 deg.
* **The high-DoLP sky band (90 deg from the sun)** decides the sky-vs-sky
  scenario only; at mid-morning and mid-afternoon the heliostats reflect
  sky near it, but two tracking neighbours see nearly the same part of it,
  so even there the DoLP difference stays far below 0.2.
* **Why the model's afternoon window is later and its windows wider than
  the paper's.** Not modelled: shadows of the heliostats on the ground
  (the ground just past a mirror's lower edge is often in that mirror's
  shadow, lit by skylight only, with a different AoP) and on each other,
  exposure and noise at low sun, and the paper's practical limits (the
  paper states its windows for the sky-vs-sky scenario and the waypoints it
  could fly). These all act most in the late afternoon and early morning.
  The predicted windows also depend on the aim point: with OpenCSP's UFACET
  aim point (60, 8.8, 28.9) m, East of the tower, the symmetry is broken
  (minimum about 12:40 instead of 13:00 in May; mornings weak, below 0.5 in
  May and below 0.3 at the equinox; afternoons strong, up to 0.89).

The numbers come from :func:`sweep_day` with the defaults (``pihim windows
--date 2021-05-13`` and ``--date 2021-03-20``); they depend on the planner's
geometry, which may still change.

Speed: a 10-minute NSTTF sweep (73 times in May; per time about 70 ms of
tracking and planning and 80 ms of scoring with the shift search) takes
6.8-10.8 s in one process on this project's 2-core machine, depending on the
hour of its shared host, and 5.3 s in two forked workers
(``sweep_day(workers=2)``; ``benchmarks/bench_windows.py``, BENCHMARKS.md).

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), sec. 4.1 (favourable NSTTF windows
   9:30-11:30 and 14:00-16:00 local time), sec. 4.2, sec. 5.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim import _forked
from pihim._atomic import atomic_path, write_text_atomic
from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.planning.scoring import (
    DEFAULT_SHIFT_SEARCH,
    ScoringModel,
    ShiftSearch,
    build_scene,
    coverage,
    score_passes,
)
from pihim.sky.sun import NSTTF, Site, check_year, parse_site, sun_position

__all__ = [
    "DEFAULT_MAX_ALTITUDE_M",
    "FRACTION_KINDS",
    "PAPER_WINDOWS_LOCAL",
    "DaySweep",
    "Window",
    "is_nsttf",
    "local_timezone",
    "paper_agreement",
    "parse_date",
    "sweep_day",
    "write_windows_csv",
    "write_windows_png",
]

#: The paper's favourable windows at the NSTTF, local time (sec. 4.1).
PAPER_WINDOWS_LOCAL: tuple[tuple[str, str], ...] = (("09:30", "11:30"), ("14:00", "16:00"))
#: Highest flight altitude of the sweep's plans by default, metres above the field origin
#: (the planner's default, OpenCSP's NSTTF UFACET case).
DEFAULT_MAX_ALTITUDE_M = 25.0
FractionKind = Literal["sky", "ground", "either", "planned"]
FRACTION_KINDS: tuple[str, ...] = ("sky", "ground", "either", "planned")
CSV_COLUMNS = ("time", "sun_zenith_deg", "sun_azimuth_deg", "sun_elevation_deg", "fraction_planned",
               "fraction_sky", "fraction_ground", "fraction_either")


def parse_date(text: str | _dt.date) -> _dt.date:
    """A calendar date from ``YYYY-MM-DD`` (a ``datetime.date`` is returned unchanged).

    Raises
    ------
    PihimInputError
        Malformed text, or a year outside :data:`pihim.sky.sun.YEAR_RANGE`.
    """
    if isinstance(text, (_dt.date, _dt.datetime)):
        day = text.date() if isinstance(text, _dt.datetime) else text
        check_year(day.year, str(day))
        return day
    try:
        s = str(text).strip()
        if len(s) != 10:
            raise ValueError
        day = _dt.date.fromisoformat(s)
    except ValueError:
        raise PihimInputError(f"date {text!r} is not a calendar date YYYY-MM-DD (e.g. 2021-05-13)") from None
    check_year(day.year, text)
    return day


def local_timezone(site: Site) -> Any:
    """The site's local time zone.

    ``site.timezone`` unless it is ``"UTC"`` at a longitude more than 7.5 deg
    from Greenwich (a custom ``LAT,LON,H`` site has no named zone): then the
    fixed offset ``round(longitude / 15)`` hours, i.e. approximate mean
    solar time, so that the sweep covers the site's own day.
    """
    if site.timezone and site.timezone.upper() != "UTC":
        return site.timezone
    hours = round(float(site.longitude_deg) / 15.0)
    if hours == 0:
        return "UTC"
    return _dt.timezone(_dt.timedelta(hours=hours))


@dataclass(frozen=True)
class Window:
    """A contiguous run of sweep samples at or above a threshold.

    ``start`` and ``end`` are the first and last sample times in the run
    (local, timezone-aware); a run of one sample has zero duration.
    """

    start: _dt.datetime
    end: _dt.datetime
    peak_fraction: float
    mean_fraction: float

    @property
    def duration_min(self) -> float:
        """``end - start`` in minutes (elapsed time, also across a DST change)."""
        return _elapsed_s(self.start, self.end) / 60.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly record (ISO 8601 times with offsets)."""
        return {"start": self.start.isoformat(), "end": self.end.isoformat(), "duration_min": self.duration_min,
                "peak_fraction": self.peak_fraction, "mean_fraction": self.mean_fraction}


@dataclass(frozen=True, eq=False)
class DaySweep:
    """Fractions of the field coverable with usable contrast through one day.

    Arrays have one entry per sampled time (sun above ``min_elevation_deg``).

    Attributes
    ----------
    date : datetime.date
        The local calendar day swept.
    site : Site
    timezone : str or datetime.tzinfo
        Local time zone of ``times``.
    times : tuple of datetime.datetime
        Sample times, local and timezone-aware (pandas is not needed: the
        sweep's command starts without importing it).
    sun_zenith_deg, sun_azimuth_deg : ndarray
        Apparent sun position, degrees (azimuth clockwise from North).
    fraction_planned, fraction_sky, fraction_ground, fraction_either : ndarray
        Fractions of the field's heliostats in [0, 1] (module notes).
    n_heliostats : int
    step_min, min_elevation_deg : float
    n_images : ndarray of int
        Planned images per time.
    shifted_passes : ndarray of int
        Passes moved by the contrast search per time.
    settings : dict
        The sweep's inputs (aim point, altitude limit, models), JSON-ready.
    planner_errors : tuple of (str, str)
        ``(time ISO, message)`` where the planner refused to plan (e.g. no
        safe altitude below the limit); those times count as nothing
        coverable.
    """

    date: _dt.date
    site: Site
    timezone: Any
    times: tuple[_dt.datetime, ...]
    sun_zenith_deg: NDArray[np.float64]
    sun_azimuth_deg: NDArray[np.float64]
    fraction_planned: NDArray[np.float64]
    fraction_sky: NDArray[np.float64]
    fraction_ground: NDArray[np.float64]
    fraction_either: NDArray[np.float64]
    n_heliostats: int
    step_min: float
    min_elevation_deg: float
    n_images: NDArray[np.int64]
    shifted_passes: NDArray[np.int64]
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)
    planner_errors: tuple[tuple[str, str], ...] = ()

    def __len__(self) -> int:
        return len(self.times)

    @property
    def sun_elevation_deg(self) -> NDArray[np.float64]:
        """90 - zenith, degrees."""
        return 90.0 - self.sun_zenith_deg

    def fractions(self, which: str = "either") -> NDArray[np.float64]:
        """One of the fraction arrays: ``"sky"``, ``"ground"``, ``"either"`` or ``"planned"``."""
        if which not in FRACTION_KINDS:
            raise PihimInputError(f"unknown fraction {which!r}; choose one of {', '.join(FRACTION_KINDS)}")
        return getattr(self, f"fraction_{which}")

    def windows(self, threshold: float = 0.5, which: str = "either", *, relative: bool = False,
                min_duration_min: float = 0.0) -> tuple[Window, ...]:
        """Contiguous runs of samples with the chosen fraction ``>= threshold``.

        Samples more than 1.5 steps apart (a gap in the sampled times) break
        a run.

        Parameters
        ----------
        threshold : float
            Fraction of the field's heliostats, in [0, 1]; with ``relative``,
            a fraction of the day's best value instead.
        which : {"either", "sky", "ground", "planned"}
            The fraction judged.
        relative : bool
            Judge ``fraction >= threshold * max(fraction)`` (a day whose best
            is 0 has no window).
        min_duration_min : float
            Drop runs shorter than this, minutes.
        """
        if not (isinstance(threshold, (int, float)) and 0.0 <= threshold <= 1.0):
            raise PihimInputError(f"threshold must be a fraction in [0, 1], got {threshold!r}")
        f = self.fractions(which)
        level = threshold * (float(np.max(f)) if len(f) else 0.0) if relative else threshold
        good = (f >= level - 1e-12) & (f > 0.0 if relative else True)
        out: list[Window] = []
        i, n = 0, len(f)
        gap_s = 1.5 * self.step_min * 60.0
        while i < n:
            if not good[i]:
                i += 1
                continue
            j = i
            while j + 1 < n and good[j + 1] and _elapsed_s(self.times[j], self.times[j + 1]) <= gap_s:
                j += 1
            w = Window(self.times[i], self.times[j], float(np.max(f[i : j + 1])), float(np.mean(f[i : j + 1])))
            if w.duration_min >= min_duration_min:
                out.append(w)
            i = j + 1
        return tuple(out)

    def rows(self) -> list[dict[str, Any]]:
        """One dict per time with the CSV columns (:data:`CSV_COLUMNS`)."""
        return [
            {
                "time": t.isoformat(),
                "sun_zenith_deg": float(z),
                "sun_azimuth_deg": float(a),
                "sun_elevation_deg": float(90.0 - z),
                "fraction_planned": float(fp),
                "fraction_sky": float(fs),
                "fraction_ground": float(fg),
                "fraction_either": float(fe),
            }
            for t, z, a, fp, fs, fg, fe in zip(self.times, self.sun_zenith_deg, self.sun_azimuth_deg,
                                               self.fraction_planned, self.fraction_sky, self.fraction_ground,
                                               self.fraction_either, strict=True)
        ]

    def summary(self, threshold: float = 0.5, which: str = "either", *, relative: bool = False) -> dict[str, Any]:
        """JSON-ready summary: settings, windows, best time, agreement with the paper (NSTTF only)."""
        f = self.fractions(which)
        level = threshold * (float(np.max(f)) if len(f) else 0.0) if relative else threshold
        best = int(np.argmax(f)) if len(f) else None
        out: dict[str, Any] = {
            "date": self.date.isoformat(),
            "site": self.site.as_dict(),
            "timezone": str(self.timezone),
            "step_min": self.step_min,
            "min_elevation_deg": self.min_elevation_deg,
            "n_times": len(self),
            "n_heliostats": self.n_heliostats,
            "threshold": threshold,
            "relative": bool(relative),
            "threshold_fraction": level,
            "fraction": which,
            "windows": [w.as_dict() for w in self.windows(threshold, which, relative=relative)],
            "best": None if best is None else {"time": self.times[best].isoformat(), "fraction": float(f[best])},
            "mean_fractions": {k: (float(np.mean(self.fractions(k))) if len(self) else None) for k in FRACTION_KINDS},
            "settings": self.settings,
            "planner_errors": [list(e) for e in self.planner_errors],
        }
        if is_nsttf(self.site):
            out["paper_agreement"] = paper_agreement(self, level, which)
        return out


def is_nsttf(site: Site) -> bool:
    """Whether ``site`` is the NSTTF (same latitude and longitude as :data:`pihim.sky.sun.NSTTF`)."""
    return (abs(site.latitude_deg - NSTTF.latitude_deg) < 1e-6 and abs(site.longitude_deg - NSTTF.longitude_deg) < 1e-6)


def _paper_mask(sweep: DaySweep) -> NDArray[np.bool_]:
    minutes = np.array([t.hour * 60 + t.minute + t.second / 60.0 for t in sweep.times], dtype=float)
    mask = np.zeros(len(minutes), dtype=bool)
    for a, b in PAPER_WINDOWS_LOCAL:
        ha, ma = (int(v) for v in a.split(":"))
        hb, mb = (int(v) for v in b.split(":"))
        mask |= (minutes >= ha * 60 + ma) & (minutes <= hb * 60 + mb)
    return mask


def paper_agreement(sweep: DaySweep, threshold: float = 0.5, which: str = "either") -> dict[str, Any]:
    """How the sweep compares with the paper's NSTTF windows (9:30-11:30, 14:00-16:00 local).

    Returns
    -------
    dict
        ``mean_inside`` / ``mean_outside``: mean fraction at samples inside /
        outside the paper's windows; ``paper_covered``: share of the samples
        inside the paper's windows that the sweep finds favourable;
        ``favourable_inside_paper``: share of the favourable samples that lie
        inside the paper's windows; ``jaccard``: |both| / |either|.
    """
    f = sweep.fractions(which)
    inside = _paper_mask(sweep)
    good = f >= threshold - 1e-12

    def frac(num: int, den: int) -> float | None:
        return num / den if den else None

    return {
        "paper_windows_local": [list(w) for w in PAPER_WINDOWS_LOCAL],
        "mean_inside": float(np.mean(f[inside])) if inside.any() else None,
        "mean_outside": float(np.mean(f[~inside])) if (~inside).any() else None,
        "paper_covered": frac(int(np.sum(good & inside)), int(np.sum(inside))),
        "favourable_inside_paper": frac(int(np.sum(good & inside)), int(np.sum(good))),
        "jaccard": frac(int(np.sum(good & inside)), int(np.sum(good | inside))),
    }


def _tzinfo(tz: Any) -> _dt.tzinfo:
    """``tz`` as a :class:`datetime.tzinfo`: an IANA name (``zoneinfo``), ``"UTC"`` or a tzinfo."""
    if isinstance(tz, _dt.tzinfo):
        return tz
    if str(tz).upper() == "UTC":
        return _dt.UTC
    from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

    try:
        return ZoneInfo(str(tz))
    except (ZoneInfoNotFoundError, ValueError):
        raise PihimInputError(f"unknown time zone {tz!r} (an IANA name such as America/Denver)") from None


def _elapsed_s(a: _dt.datetime, b: _dt.datetime) -> float:
    """``b - a`` in seconds of elapsed time (Python subtracts aware times of one zone as wall clock times)."""
    return (b.astimezone(_dt.UTC) - a.astimezone(_dt.UTC)).total_seconds()


def _midnight(date: _dt.date, tz: Any) -> _dt.datetime:
    """Local midnight starting ``date`` in ``tz``, timezone-aware."""
    return _dt.datetime.combine(date, _dt.time(0), tzinfo=_tzinfo(tz))


def _day_times(date: _dt.date, tz: Any, step_min: float) -> tuple[_dt.datetime, ...]:
    """Times every ``step_min`` minutes of elapsed time from local midnight to the next (23 or 25 h on DST days)."""
    zone = _tzinfo(tz)
    start = _midnight(date, zone).astimezone(_dt.UTC)
    end = _midnight(date + _dt.timedelta(days=1), zone).astimezone(_dt.UTC)
    n = math.floor((end - start).total_seconds() / (step_min * 60.0) + 1e-9)
    return tuple((start + _dt.timedelta(minutes=step_min * k)).astimezone(zone) for k in range(n))


@dataclasses.dataclass(frozen=True)
class _SweepJob:
    """What every time of a day sweep shares (sun vectors by time index)."""

    field: Any
    sun_vectors: NDArray[np.float64]
    aim: NDArray[np.float64]
    site: Site
    camera: CameraModel
    model: ScoringModel
    search: ShiftSearch | None
    planner: Callable[..., Sequence[Any]]
    planner_kwargs: dict[str, Any]
    max_altitude_m: float


@dataclasses.dataclass(frozen=True)
class _InstantResult:
    """What one time of the sweep adds to :class:`DaySweep` (fractions by kind, counts, the planner's refusal)."""

    fractions: dict[str, float]
    n_images: int
    shifted: int
    planner_error: str | None


def _score_instant(job: _SweepJob, i: int) -> _InstantResult:
    """Track the field at time ``i``, plan its passes, score them (with shifts) and count the coverage."""
    from pihim.field import track_field

    sun = job.sun_vectors[i]
    pose = track_field(job.field, sun, job.aim)
    error = None
    try:
        passes = job.planner(job.field, pose, aim_point=job.aim, origin=job.site, camera=job.camera,
                             max_altitude_m=job.max_altitude_m, **job.planner_kwargs)
    except PihimInputError as exc:  # e.g. no safe altitude below the limit at this sun: nothing coverable
        passes, error = (), str(exc)
    scene = build_scene(pose, sun, job.model)
    scored = score_passes(passes, pose, sun, scene=scene, search=job.search, camera=job.camera, aim_point=job.aim,
                          origin=job.site)
    cov = coverage(scored, len(job.field))
    return _InstantResult({k: float(cov[k]) for k in FRACTION_KINDS}, sum(len(p.predictions) for p in scored),
                          sum(p.shift is not None for p in scored), error)


#: Most worker processes ``workers=None`` starts (each a forked copy of the caller; ~170 MB resident each for NSTTF).
DEFAULT_MAX_WORKERS = _forked.DEFAULT_MAX_WORKERS
#: Most worker processes accepted at all.
MAX_WORKERS = _forked.MAX_WORKERS


def _run_instants(job: _SweepJob, n: int, workers: int | None) -> Iterator[tuple[int, _InstantResult]]:
    """``(i, result)`` for every time index, in order of completion.

    With more than one worker (on Linux), the times go to a pool of forked
    processes one at a time (their costs differ by 2-3x over the day); the
    children inherit ``job`` (planner closures included) and the compiled
    kernels, and return only small results (:func:`pihim._forked.imap_unordered`).
    """
    return _forked.imap_unordered(functools.partial(_score_instant, job), n, workers, what="day-sweep times")


def sweep_day(
    date: str | _dt.date,
    *,
    site: Site | str = NSTTF,
    field: Any = None,
    aim_point: ArrayLike | None = None,
    step_min: float = 10.0,
    min_elevation_deg: float = 10.0,
    max_altitude_m: float = DEFAULT_MAX_ALTITUDE_M,
    camera: CameraModel | None = None,
    model: ScoringModel | None = None,
    search: ShiftSearch | None = DEFAULT_SHIFT_SEARCH,
    planner: Callable[..., Sequence[Any]] | None = None,
    planner_kwargs: dict[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    workers: int | None = 1,
) -> DaySweep:
    """Plan and score the field every ``step_min`` minutes of a day.

    Parameters
    ----------
    date : str or datetime.date
        ``YYYY-MM-DD``, a calendar day in the site's local time
        (:func:`local_timezone`).
    site : Site or str
        Default :data:`pihim.sky.sun.NSTTF`; ``"LAT,LON,H"`` accepted.
    field : Field, optional
        Default :func:`pihim.field.nsttf_like_field`.
    aim_point : array_like, shape (3,), optional
        Where the field reflects the sun during the scan, ENU metres; default
        the field's tower target (the field in operation, as the paper
        recommends for scanning, sec. 4.1). OpenCSP's dedicated UFACET
        flights aim at (60, 8.8, 28.9) m (:data:`pihim.field.UFACET_AIM_POINT`).
    step_min : float
        Sampling step, minutes (0.5 to 240).
    min_elevation_deg : float
        Only times with the apparent sun at least this high, degrees
        (0 to 89).
    max_altitude_m : float
        Highest flight altitude for the planner and the shifts, metres above
        the field origin.
    camera : CameraModel, optional
        Default Triton + 35 mm.
    model : ScoringModel, optional
        Scoring physics (defaults of :class:`ScoringModel`).
    search : ShiftSearch or None
        Shift search (its ``max_altitude_m`` is capped at ``max_altitude_m``);
        ``None`` scores the plans as planned.
    planner : callable, optional
        ``planner(field, pose, aim_point=, origin=, camera=, max_altitude_m=,
        **planner_kwargs) -> passes``; default
        :func:`pihim.planning.ufacet.plan_passes`.
    planner_kwargs : dict, optional
        Extra keyword arguments for the planner.
    progress : callable, optional
        Called as ``progress(done, total)`` after each time (in this
        process, also with ``workers`` > 1).
    workers : int or None
        Processes that plan and score the times side by side (each time is
        independent), 1 to :data:`MAX_WORKERS`; default 1 (this process
        only); None, one per CPU this process may run on, at most
        :data:`DEFAULT_MAX_WORKERS`. With more
        than one, on Linux, the times are shared among forked copies of this
        process (so ``planner`` and its arguments need not be picklable) and
        the result is identical to one process's; elsewhere (no safe
        ``fork``) the sweep runs in this process. Parallel runs cut the wall
        time, not the CPU time. A worker that dies leaves its unfinished
        times to this process (a ``RuntimeWarning``). ``planner`` must not
        rely on side effects: in a worker they stay in the worker. As with
        any ``fork``, only the calling thread is copied: call it with
        ``workers`` > 1 from a process whose other threads hold no locks
        the workers need (numba compiling, logging), e.g. not while another
        thread compiles kernels.

    Returns
    -------
    DaySweep

    Raises
    ------
    PihimInputError
        Malformed date or site, out-of-range step or elevation limit, no
        aim point for a field without a tower, ``workers`` not None or an
        integer >= 1.
    """
    day = parse_date(date)
    site = parse_site(site)
    _forked.check_workers(workers)
    if not (isinstance(step_min, (int, float)) and math.isfinite(step_min) and 0.5 <= step_min <= 240.0):
        raise PihimInputError(f"step must be between 0.5 and 240 minutes, got {step_min!r}")
    if not (isinstance(min_elevation_deg, (int, float)) and 0.0 <= min_elevation_deg < 89.0):
        raise PihimInputError(f"minimum sun elevation must be in [0, 89) deg, got {min_elevation_deg!r}")
    from pihim.planning.ufacet import MAX_ALTITUDE_LIMIT_M

    if not (isinstance(max_altitude_m, (int, float)) and math.isfinite(max_altitude_m)
            and 0 < max_altitude_m <= MAX_ALTITUDE_LIMIT_M):
        raise PihimInputError(f"maximum altitude must be in (0, {MAX_ALTITUDE_LIMIT_M:g}] m, got {max_altitude_m!r}")
    from pihim.field import nsttf_like_field

    fld = nsttf_like_field() if field is None else field
    if aim_point is None and getattr(fld, "tower", None) is None:
        raise PihimInputError("this field has no tower: give the aim point the heliostats track toward")
    aim = np.array(fld.default_aim_point if aim_point is None else aim_point, dtype=float).reshape(-1)
    if aim.shape != (3,) or not np.all(np.isfinite(aim)):
        raise PihimInputError(f"aim point must be three finite coordinates, got {aim_point!r}")
    if aim[2] <= 0.0:
        raise PihimInputError(f"aim point must be above the ground (z > 0), got z = {aim[2]:g} m")
    if planner is None:
        from pihim.planning.ufacet import plan_passes as planner
    camera = CameraModel() if camera is None else camera
    model = ScoringModel() if model is None else model
    if search is not None:
        search = dataclasses.replace(search, max_altitude_m=min(search.max_altitude_m, float(max_altitude_m)))
        if search.min_altitude_m is not None and search.min_altitude_m >= search.max_altitude_m:
            raise PihimInputError("the shift search's minimum altitude is not below the maximum altitude")
    tz = local_timezone(site)
    times = _day_times(day, tz, float(step_min))
    sun = sun_position(site, times)
    keep = np.asarray(sun.elevation_deg, dtype=float) >= float(min_elevation_deg)
    times = tuple(t for t, k in zip(times, keep, strict=True) if k)
    zen = np.asarray(sun.zenith_deg, dtype=float)[keep]
    azi = np.asarray(sun.azimuth_deg, dtype=float)[keep]
    vecs = np.asarray(sun.vector, dtype=float).reshape(-1, 3)[keep]
    n = len(times)
    fr = {k: np.zeros(n) for k in FRACTION_KINDS}
    n_images = np.zeros(n, dtype=np.int64)
    shifted = np.zeros(n, dtype=np.int64)
    job = _SweepJob(fld, vecs, aim, site, camera, model, search, planner, dict(planner_kwargs or {}),
                    float(max_altitude_m))
    failed: list[tuple[int, str]] = []
    for done, (i, result) in enumerate(_run_instants(job, n, workers), start=1):
        for k in FRACTION_KINDS:
            fr[k][i] = result.fractions[k]
        n_images[i] = result.n_images
        shifted[i] = result.shifted
        if result.planner_error is not None:
            failed.append((i, result.planner_error))
        if progress is not None:
            progress(done, n)
    errors = [(times[i].isoformat(), message) for i, message in sorted(failed)]
    settings = {
        "aim_point_m": aim.tolist(),
        "max_altitude_m": float(max_altitude_m),
        "field_heliostats": len(fld),
        "sky": model.sky.describe(),
        "sky_irradiance_w_m2": float(model.sky_irradiance_w_m2),
        "mirror": type(model.mirror).__name__,
        "ground": {"sigma_deg": model.ground.sigma_deg, "refractive_index": model.ground.refractive_index,
                   "sun_irradiance_w_m2": model.ground.sun_irradiance},
        "shift_search": None if search is None else {
            "altitude_deltas_m": list(search.altitude_deltas_m), "lateral_offsets_m": list(search.lateral_offsets_m),
            "gaze_deltas_deg": list(search.gaze_deltas_deg), "max_altitude_m": search.max_altitude_m},
    }
    return DaySweep(
        date=day, site=site, timezone=tz, times=times, sun_zenith_deg=zen, sun_azimuth_deg=azi,
        fraction_planned=fr["planned"], fraction_sky=fr["sky"], fraction_ground=fr["ground"],
        fraction_either=fr["either"], n_heliostats=len(fld), step_min=float(step_min),
        min_elevation_deg=float(min_elevation_deg), n_images=n_images, shifted_passes=shifted, settings=settings,
        planner_errors=tuple(errors),
    )


def write_windows_csv(sweep: DaySweep, path: str | Path) -> Path:
    """Write the sweep as CSV (:data:`CSV_COLUMNS`; times ISO 8601 with offsets), atomically."""
    lines = [",".join(CSV_COLUMNS)]
    for row in sweep.rows():
        lines.append(",".join(row["time"] if c == "time" else f"{row[c]:.6g}" for c in CSV_COLUMNS))
    return write_text_atomic(path, "\n".join(lines) + "\n")


def _hours(sweep: DaySweep, ts: Sequence[_dt.datetime]) -> NDArray[np.float64]:
    day0 = _midnight(sweep.date, sweep.timezone)
    return np.array([_elapsed_s(day0, t) / 3600.0 for t in ts], dtype=float)


def write_windows_png(sweep: DaySweep, path: str | Path, *, threshold: float = 0.5, which: str = "either",
                      relative: bool = False) -> Path:
    """Plot the fractions against local time with the favourable windows shaded, atomically.

    Favourable windows (:meth:`DaySweep.windows`) are shaded green (each
    extended by half a step on both sides); at the NSTTF the paper's windows
    are drawn as hatched bands. The threshold is a dashed line.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    level = threshold * (float(np.max(sweep.fractions(which))) if len(sweep) else 0.0) if relative else threshold
    fig = Figure(figsize=(8.0, 5.2), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = _hours(sweep, sweep.times)
    half = sweep.step_min / 120.0
    for k, w in enumerate(sweep.windows(threshold, which, relative=relative)):
        a, b = _hours(sweep, [w.start, w.end])
        ax.axvspan(a - half, b + half, color="tab:green", alpha=0.18, lw=0, label="favourable (model)" if k == 0 else None)
    if is_nsttf(sweep.site):
        for k, (a, b) in enumerate(PAPER_WINDOWS_LOCAL):
            ha = int(a[:2]) + int(a[3:]) / 60.0
            hb = int(b[:2]) + int(b[3:]) / 60.0
            ax.axvspan(ha, hb, facecolor="none", edgecolor="tab:purple", hatch="//", lw=0.8,
                       label="paper windows (NSTTF)" if k == 0 else None)
    styles = (("either", "either scenario", "k", "-"), ("ground", "ground-vs-ground", "tab:brown", "--"),
              ("sky", "sky-vs-sky", "tab:blue", ":"), ("planned", "planned (geometry)", "0.6", "-."))
    for key, label, colour, ls in styles:
        ax.plot(x, sweep.fractions(key), color=colour, ls=ls, lw=1.6 if key == "either" else 1.2, marker="." if
                len(x) < 40 else None, label=label)
    label = f"threshold {threshold:g} x day's best" if relative else f"threshold {threshold:g}"
    ax.axhline(level, color="0.3", ls="--", lw=0.8, label=label)
    ax.set_xlim(float(np.min(x)) - 0.5 if len(x) else 0.0, float(np.max(x)) + 0.5 if len(x) else 24.0)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel(f"local time (h), {sweep.timezone}")
    ax.set_ylabel("fraction of heliostats with a usable image")
    ax.set_title(f"{sweep.site.name} {sweep.date.isoformat()}: polarimetric inspection windows "
                 f"(sun > {sweep.min_elevation_deg:g} deg, every {sweep.step_min:g} min)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncols=4, frameon=False)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)
