"""Speed and accuracy benchmark of the rough-ground polarization model.

Rows (each timed ``repeat`` times after ``warmup`` untimed calls, in one
process, one after the other; sun at zenith 30 deg, azimuth 235 deg as in the
paper's Fig. 2c-d; ground :class:`pihim.surfaces.ground.GroundModel` with its
defaults, sigma 15 deg):

``det map 1 deg, sun+sky``
    :meth:`GroundModel.stokes` on the 90 x 360 bin centres of
    :func:`hemisphere_grid(1.0)` (32,400 view directions) with the sun and a
    sky; the sky is tabulated (257^2 directions) and integrated by the numba
    kernel with 16 x 32 facet-normal nodes. Target: <= 0.5 s median.
``one map in a new process``
    What ``pihim ground`` pays for its one map: a fresh Python process
    (started with the collector's thresholds of the ``pihim`` script, and
    again with CPython's defaults, as a program importing pihim would)
    imports pihim, builds the 1-deg grid and the sky, and calls
    :meth:`GroundModel.stokes` once (numba's cache warm, as after a first
    run: the first call loads the compiled kernels and numba's type
    registries), then a second time. Wall and CPU time of each step; the
    first call is held to the same 0.5 s.
``det map 1 deg, sun only``
    The closed-form sun term alone (numpy).
``numpy sky integrand``
    The same sky term with the numpy integrand on the same table and nodes
    (a 1-in-``k`` subset of the directions, time scaled by ``k``): what the
    numba kernel buys.
``direct sky (numpy)``
    The reference route (sky called at every quadrature direction), subset
    and scaled likewise.
``det map 0.5 deg``
    The deterministic route on the Monte Carlo's 180 x 720 bin centres.
``MC 100k, 0.5 deg``
    The paper's Monte Carlo (100,000 microfacets, 0.5 deg bins), sun only
    and sun + one sky ray per facet; and with 400,000 and 1,600,000 facets
    (not with ``--quick``) to fit the time as ``a + b N`` and to follow the
    error's decay.

Sky: :class:`pihim.sky.model.SkyModel` (Rayleigh, dmax 0.8, CIE clear-sky
radiance scaled to ``SKY_SCALE`` at the zenith).

Accuracy and "equal accuracy"
-----------------------------
The quantity both routes estimate is the bin average of the Stokes radiance
(projected-solid-angle weighted). The *reference* is that bin average
computed deterministically with 4 x 4 midpoints per bin and 32 x 64
facet-normal nodes. The *error* of a map is the RMS, over evaluation bins,
of the relative S0 error ``(S0 - S0_ref) / S0_ref`` (DoLP and AoP errors are
reported too). Evaluation bins: for the sun only, all bins where the
reference S0 is >= 5 % of its maximum (the glint lobe); for sun + sky, 3000
random bins of the hemisphere. The Monte Carlo's error falls as
``N^-1/2`` asymptotically (the measured exponent of the last pair of runs
is reported), so from the largest run it reaches the deterministic map's
error with ``N_eq = N (err_MC / err_det)^2`` facets, which take
``a + b N_eq`` seconds (least-squares line through the timed runs).
Speed-up at equal accuracy = that time / the deterministic map's time on
the same 0.5 deg grid. It is an extrapolation (nobody runs 10^12 facets);
the measured ratio at equal *grid* (where the deterministic map is far more
accurate) is reported beside it as a lower bound.

Run ``python benchmarks/run.py --only bench_ground`` or this file directly.
"""

from __future__ import annotations

import gc
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numba
import numpy as np

from pihim.polarimetry.frames import (
    aop4_deg,
    dolp4,
    dot,
    normalize,
    perpendicular_reference,
)
from pihim.sky.model import SkyModel
from pihim.surfaces.ground import (
    GroundModel,
    HemisphereGrid,
    _sky_integral_numpy,
    _SkyTable,
    hemisphere_grid,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=10, warmup=1, quick_repeat=3, quick_warmup=1)
SUN_ZEN_DEG, SUN_AZ_DEG = 30.0, 235.0
SKY_SCALE = 30.0  # W m^-2 sr^-1 at the zenith, order of a clear sky's broadband radiance
TARGET_MAP_S = 0.5
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "ground.json"
REFERENCE_SUB = 4
REFERENCE_QUADRATURE = (32, 64)
SKY_EVAL_BINS = 3000
LOBE_FRACTION = 0.05
SEED = 20260101


def direction(zen_deg: float, az_deg: float) -> np.ndarray:
    """ENU unit vector from zenith and azimuth (clockwise from North), degrees."""
    z, a = math.radians(zen_deg), math.radians(az_deg)
    return np.array([math.sin(z) * math.sin(a), math.sin(z) * math.cos(a), math.cos(z)])


def skies() -> tuple[dict[str, Any], list[str]]:
    """The sky used: pihim's Rayleigh :class:`~pihim.sky.model.SkyModel` with CIE clear-sky radiance."""
    return {"pihim": SkyModel(scale=SKY_SCALE)}, []


# ---------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------
def time_call(fn: Callable[[], Any], repeat: int, warmup: int) -> dict[str, Any]:
    """Median, p10, p90 and first-call wall time (s) of ``fn``, and the CPU share of other processes.

    The first call counts as the first of the ``warmup`` untimed calls.
    """
    gc.collect()
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    for _ in range(max(0, warmup - 1)):
        fn()
    cpu0 = time.process_time()
    samples, load = harness.time_calls(fn, repeat)
    cpu_s = (time.process_time() - cpu0) / repeat
    median, p10, p90 = (float(v) / 1e3 for v in np.percentile(samples, [50, 10, 90]))
    return {
        "median_s": median,
        "p10_s": p10,
        "p90_s": p90,
        "cpu_s": cpu_s,
        "first_call_s": first,
        "repeat": repeat,
        "other_cpu_load": load,
        "load_avg": harness.load_average(),
    }


_ONE_MAP = r"""
import json, sys, time
def now():
    return time.perf_counter(), time.process_time()
t0 = now()
if sys.argv[4] == "cli":  # the collector's thresholds as the pihim script starts (pihim._collector)
    from pihim._collector import relax_during_startup
    relax_during_startup()
import numpy as np
from pihim.sky.model import SkyModel
from pihim.surfaces.ground import GroundModel, hemisphere_grid
t1 = now()
zen, az, scale = (float(a) for a in sys.argv[1:4])
z, a = np.radians(zen), np.radians(az)
sun = np.array([np.sin(z) * np.sin(a), np.sin(z) * np.cos(a), np.cos(z)])
model, sky, v = GroundModel(), SkyModel(scale=scale), hemisphere_grid(1.0).directions
t2 = now()
model.stokes(v, sun, sky)
t3 = now()
model.stokes(v, sun, sky)
t4 = now()
steps = {"import": (t0, t1), "setup": (t1, t2), "first_call": (t2, t3), "second_call": (t3, t4)}
print(json.dumps({f"{k}_{u}": b[i] - a[i] for k, (a, b) in steps.items() for i, u in enumerate(("s", "cpu_s"))}))
"""


def one_map_in_new_process(cli: bool = True) -> dict[str, Any]:
    """:data:`_ONE_MAP` in a fresh process, after an untimed run of it (numba's cache as after a first run).

    With ``cli``, the process starts as the ``pihim`` script does, with the collector's thresholds raised
    (:mod:`pihim._collector`); without, as a program importing pihim (CPython's default thresholds).
    """
    import json

    argv = [sys.executable, "-c", _ONE_MAP, str(SUN_ZEN_DEG), str(SUN_AZ_DEG), str(SKY_SCALE),
            "cli" if cli else "library"]
    harness.process_run(argv)
    res = harness.process_run(argv)
    if res["returncode"] != 0:
        return {"error": res["stderr"].strip().splitlines()[-1:]}
    return {**json.loads(res["stdout"].strip().splitlines()[-1]), "process_wall_s": res["wall_s"],
            "process_cpu_s": res["cpu_s"], "other_cpu_load": res["other_cpu"], "load_avg": res["load_after"]}


# ---------------------------------------------------------------------------
# Reference bin averages and error metrics
# ---------------------------------------------------------------------------
def bin_reference(
    model: GroundModel,
    grid: HemisphereGrid,
    bins: np.ndarray,
    sun: np.ndarray,
    sky: Any,
    sub: int = REFERENCE_SUB,
    quadrature: tuple[int, int] = REFERENCE_QUADRATURE,
    chunk: int = 4096,
) -> np.ndarray:
    """Deterministic bin averages ``(K, 4)`` of the flat bins ``bins``, as :meth:`GroundModel.bin_average`."""
    na = grid.shape[1]
    step = math.radians(grid.step_deg)
    off = (np.arange(sub) + 0.5) / sub
    out = np.empty((bins.size, 4))
    for start in range(0, bins.size, chunk):
        b = bins[start : start + chunk]
        i, j = np.divmod(b, na)
        zz = (i[:, None, None] + off[None, :, None]) * step * np.ones((1, 1, sub))
        aa = (j[:, None, None] + off[None, None, :]) * step * np.ones((1, sub, 1))
        sz = np.sin(zz)
        d = np.stack([sz * np.sin(aa), sz * np.cos(aa), np.cos(zz)], axis=-1)
        ec = grid.reference.reshape(-1, 3)[b][:, None, None, :]
        e = normalize(ec - dot(ec, d)[..., None] * d)
        s, _ = model.stokes(d, sun, sky, e, quadrature=quadrature)
        w = np.cos(zz) * sz
        out[start : start + chunk] = np.sum(s * w[..., None], axis=(1, 2)) / np.sum(w, axis=(1, 2))[:, None]
    return out


def errors(est: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """RMS relative S0 error, RMS DoLP error and RMS axial AoP error (deg, where ref DoLP > 0.05)."""
    rel = (est[:, 0] - ref[:, 0]) / ref[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        p_est = np.nan_to_num(dolp4(est), nan=0.0)
    p_ref = dolp4(ref)
    pol = p_ref > 0.05
    da = np.abs(aop4_deg(est[pol]) - aop4_deg(ref[pol])) % 180.0
    da = np.where(np.isnan(da), 90.0, np.minimum(da, 180.0 - da))
    return {
        "rms_rel_s0": float(np.sqrt(np.mean(rel**2))),
        "rms_dolp": float(np.sqrt(np.mean((p_est - p_ref) ** 2))),
        "rms_aop_deg": float(np.sqrt(np.mean(da**2))) if da.size else float("nan"),
        "bins": int(ref.shape[0]),
    }


# ---------------------------------------------------------------------------
# The benchmark
# ---------------------------------------------------------------------------
def run_benchmark(repeat: int, warmup: int, quick: bool) -> dict[str, Any]:
    """All timings, accuracy figures and targets, JSON-ready."""
    model = GroundModel()
    sun = direction(SUN_ZEN_DEG, SUN_AZ_DEG)
    sky_models, notes = skies()
    grid1 = hemisphere_grid(1.0)
    grid05 = hemisphere_grid(0.5)
    v1 = grid1.directions
    subset = 40 if quick else 10
    mc_repeat = max(1, repeat // 2)
    rows: list[dict[str, Any]] = []

    def add(label: str, fn: Callable[[], Any], reps: int = repeat, scale: float = 1.0, **extra: Any) -> dict[str, Any]:
        m = time_call(fn, reps, warmup)
        for k in ("median_s", "p10_s", "p90_s", "cpu_s", "first_call_s"):
            m[k] *= scale
        row = {"label": label, "scaled_by": scale, **m, **extra}
        rows.append(row)
        return row

    # -- deterministic maps ------------------------------------------------
    map_rows = {}
    for name, sky in sky_models.items():
        map_rows[name] = add(
            f"det map 1 deg, sun+sky ({name})", lambda sky=sky: model.stokes(v1, sun, sky), directions=32_400
        )
    add("det map 1 deg, sun only", lambda: model.stokes(v1, sun), directions=32_400)

    sky = sky_models["pihim"]
    table = _SkyTable(sky, sun, 257)
    nodes, weights = model.quadrature_nodes()
    vs = v1.reshape(-1, 3)[::subset]
    es = perpendicular_reference(vs)
    kernel_row = add(
        "sky term only, numba kernel (pihim sky)",
        lambda: _kernel_only(model, v1, sun, table, nodes, weights),
        directions=32_400,
    )
    numpy_row = add(
        f"sky term only, numpy integrand, same table (1/{subset} subset, scaled)",
        lambda: _sky_integral_numpy(vs, es, nodes, weights, table.sample, model.refractive_index, True),
        reps=max(1, repeat // 3),
        scale=float(subset),
        directions=32_400,
    )
    add(
        f"det map 1 deg, sun+sky, direct sky numpy (1/{subset} subset, scaled)",
        lambda: model.stokes(vs, sun, sky, sky_method="direct"),
        reps=max(1, repeat // 3),
        scale=float(subset),
        directions=32_400,
    )
    det05_sun = add("det map 0.5 deg, sun only", lambda: model.stokes(grid05.directions, sun), directions=129_600)
    det05_sky = add(
        "det map 0.5 deg, sun+sky (pihim sky)", lambda: model.stokes(grid05.directions, sun, sky), directions=129_600
    )

    # -- Monte Carlo -----------------------------------------------------------
    sizes = (100_000, 400_000) if quick else (100_000, 400_000, 1_600_000)
    mc_rows = {}
    for label, s in (("sun", None), ("sun+sky", sky)):
        for n in sizes:
            mc_rows[(label, n)] = add(
                f"MC {n:,} facets, 0.5 deg, {label}",
                lambda s=s, n=n: model.monte_carlo(sun, s, n_facets=n, bin_deg=0.5, seed=SEED),
                reps=max(1, mc_repeat * sizes[0] // n),
                facets=n,
            )

    # -- accuracy ------------------------------------------------------------------
    accuracy: dict[str, Any] = {}
    rng = np.random.default_rng(SEED)
    det_sun_map = model.stokes(grid05.directions, sun)[0].reshape(-1, 4)
    lobe = np.nonzero(det_sun_map[:, 0] >= LOBE_FRACTION * det_sun_map[:, 0].max())[0]
    cases = {
        "sun": (None, lobe, det05_sun),
        "sun+sky": (sky, np.sort(rng.choice(grid05.directions[..., 0].size, SKY_EVAL_BINS, replace=False)), det05_sky),
    }
    for label, (s, bins, det_row) in cases.items():
        ref = bin_reference(model, grid05, bins, sun, s)
        det = model.stokes(grid05.directions, sun, s)[0].reshape(-1, 4)[bins]
        err_det = errors(det, ref)
        err_mc = {}
        for n in sizes:
            r = model.monte_carlo(sun, s, n_facets=n, bin_deg=0.5, seed=SEED)
            err_mc[n] = errors(r.stokes.reshape(-1, 4)[bins], ref)
            err_mc[n]["predicted_rms_rel_s0"] = float(
                np.sqrt(np.mean((r.stderr.reshape(-1, 4)[bins, 0] / ref[:, 0]) ** 2))
            )
        times = np.array([mc_rows[(label, n)]["median_s"] for n in sizes])
        b, a = np.polyfit(np.array(sizes, float), times, 1)
        n_max = sizes[-1]
        slope = math.log(err_mc[sizes[-2]]["rms_rel_s0"] / err_mc[n_max]["rms_rel_s0"]) / math.log(n_max / sizes[-2])
        n_eq = n_max * (err_mc[n_max]["rms_rel_s0"] / err_det["rms_rel_s0"]) ** 2
        t_eq = a + b * n_eq
        accuracy[label] = {
            "evaluation_bins": int(bins.size),
            "deterministic": err_det,
            "monte_carlo": {str(n): e for n, e in err_mc.items()},
            "mc_error_exponent_last_pair": slope,
            "mc_time_fit_s": {"a": float(a), "b_per_facet": float(b)},
            "equal_accuracy_facets": n_eq,
            "equal_accuracy_mc_time_s": t_eq,
            "deterministic_time_s": det_row["median_s"],
            "speedup_equal_accuracy": t_eq / det_row["median_s"],
            "speedup_equal_grid": mc_rows[(label, sizes[0])]["median_s"] / det_row["median_s"],
        }

    # quadrature and table errors of the 1-deg sky map (sun term is closed form)
    sky_only = GroundModel(sun_irradiance=0.0)
    base = sky_only.stokes(v1, sun, sky)[0].reshape(-1, 4)
    fine = sky_only.stokes(v1, sun, sky, quadrature=(64, 128))[0].reshape(-1, 4)
    table_fine = sky_only.stokes(v1, sun, sky, sky_table_size=1025)[0].reshape(-1, 4)
    direct = sky_only.stokes(vs, sun, sky, sky_method="direct")[0]
    accuracy["sky_map_1deg"] = {
        "quadrature_16x32_vs_64x128": errors(base, fine),
        "table_257_vs_1025": errors(base, table_fine),
        f"table_vs_direct_subset_1/{subset}": errors(base[::subset], direct),
    }

    kernel_gain = numpy_row["median_s"] / kernel_row["median_s"]
    one_map = one_map_in_new_process(cli=True)
    one_map_library = one_map_in_new_process(cli=False)
    targets = [
        harness.target(f"det map 1 deg sun+sky ({name}) median", row["median_s"], TARGET_MAP_S, "s")
        for name, row in map_rows.items()
    ] + [
        harness.target(f"det map 1 deg sun+sky ({name}) CPU time per map (all threads)", row["cpu_s"], TARGET_MAP_S,
                       "s")
        for name, row in map_rows.items()
    ] + [
        harness.target("one map in a new process as `pihim ground` starts, first call (numba cache warm)",
                       one_map.get("first_call_s"), TARGET_MAP_S, "s"),
        harness.target("one map in a new process as `pihim ground` starts, first call's CPU time",
                       one_map.get("first_call_cpu_s"), TARGET_MAP_S, "s"),
        harness.target("one map in a new process of a library user, first call", one_map_library.get("first_call_s"),
                       TARGET_MAP_S, "s"),
        harness.target("one map in a new process of a library user, first call's CPU time",
                       one_map_library.get("first_call_cpu_s"), TARGET_MAP_S, "s"),
    ]
    return {
        "benchmark": "ground",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "settings": {
            "repeat": repeat,
            "warmup": warmup,
            "quick": quick,
            "sun_zenith_deg": SUN_ZEN_DEG,
            "sun_azimuth_deg": SUN_AZ_DEG,
            "model": repr(model),
            "sky_scale": SKY_SCALE,
        },
        "machine": machine_info(),
        "results": rows,
        "one_map_new_process": one_map,
        "one_map_new_process_library": one_map_library,
        "numba_gain_sky_kernel": kernel_gain,
        "accuracy": accuracy,
        "targets": targets,
        "notes": notes,
    }


def _kernel_only(model, v, sun, table, nodes, weights):
    """The sky kernel alone on a prebuilt table (no sky evaluation, no sun term)."""
    from pihim.surfaces.ground import _sky_kernel

    vv = v.reshape(-1, 3)
    out = np.zeros((vv.shape[0], 4))
    _sky_kernel(
        vv,
        perpendicular_reference(vv),
        nodes,
        weights,
        table.table,
        table.radius,
        table.step,
        model.refractive_index,
        model.include_shadowing,
        out,
    )
    return out


def machine_info() -> dict[str, Any]:
    """CPU, numba threads and library versions."""
    return {
        "cpu_model": harness.cpu_model(),
        "cpu_count": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
    }


def _f(x: float | None, spec: str = ".3f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


NOTES = (
    (
        "Equal accuracy: the Monte Carlo facet count whose RMS relative S0 error (vs the reference bin averages) "
        "equals the deterministic map's, extrapolated from the largest run with err ~ N^-1/2 (the asymptotic rate; "
        "the measured exponent of the last pair of runs is in the table) and time = a + b N (least-squares fit of "
        "the timed runs); equal grid: the paper's 100k-facet run vs the deterministic map on the same 0.5 deg bins, "
        "the deterministic map being far more accurate."
    ),
    (
        "Reference: deterministic bin averages with 4 x 4 midpoints per bin and 32 x 64 facet-normal nodes; sun: "
        "bins with S0 >= 5 % of the maximum (glint lobe); sun+sky: 3000 random bins. Empty Monte Carlo bins count "
        "with S0 = 0 (relative error 1); DoLP of empty bins counts as 0."
    ),
    ("Scaled rows ran on a 1-in-k subset of the 1-deg directions; their time is multiplied by k."),
    (
        "Other CPU %: CPU used by other processes during the timed calls (/proc/stat); only rows near 0 % are "
        "trustworthy on this 2-core machine."
    ),
)


def markdown_report(rep: dict[str, Any]) -> str:
    """The report as markdown tables."""
    s = rep["settings"]
    lines = [
        (
            f"Ground model {s['model']}; sun at zenith {s['sun_zenith_deg']:g} deg, "
            f"azimuth {s['sun_azimuth_deg']:g} deg; {s['repeat']} timed calls after {s['warmup']} warm-up "
            "(Monte Carlo rows: fewer)."
        ),
        "",
        "| Row | Median s | p10 s | p90 s | CPU s | First call s | Other CPU % | Load |",
        "|---|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for r in rep["results"]:
        load = None if r["other_cpu_load"] is None else 100 * r["other_cpu_load"]
        lines.append(
            f"| {r['label']} | {_f(r['median_s'], '.4f')} | {_f(r['p10_s'], '.4f')} | {_f(r['p90_s'], '.4f')} "
            f"| {_f(r.get('cpu_s'), '.4f')} | {_f(r['first_call_s'], '.3f')} | {_f(load, '.0f')} "
            f"| {_f(r.get('load_avg'), '.1f')} |"
        )
    gain = rep["numba_gain_sky_kernel"]
    lines += ["", f"numba sky kernel vs numpy integrand on the same table and nodes: {gain:.0f}x faster."]
    lines += ["", "One map (1 deg, sun + sky) in a new process, numba's cache warm; wall s (CPU s):", "",
              "| process | import | grid, sky, model | first call | second call | process |",
              "|---|--:|--:|--:|--:|--:|"]
    for label, key in (("as `pihim ground` starts", "one_map_new_process"),
                       ("a library user's", "one_map_new_process_library")):
        o = rep.get(key, {"error": "not run"})
        if "error" in o:
            lines.append(f"| {label} | error {o['error']} | | | | |")
            continue
        lines.append(f"| {label} | {o['import_s']:.3f} ({o['import_cpu_s']:.3f}) "
                     f"| {o['setup_s']:.3f} ({o['setup_cpu_s']:.3f}) "
                     f"| {o['first_call_s']:.3f} ({o['first_call_cpu_s']:.3f}) "
                     f"| {o['second_call_s']:.3f} ({o['second_call_cpu_s']:.3f}) "
                     f"| {o['process_wall_s']:.2f} ({o['process_cpu_s']:.2f}) |")
    lines += [
        "",
        "| Accuracy vs reference bin averages (0.5 deg bins) | Bins | RMS rel S0 | RMS DoLP | RMS AoP deg |",
        "|---|--:|--:|--:|--:|",
    ]
    for label in ("sun", "sun+sky"):
        a = rep["accuracy"][label]
        d = a["deterministic"]
        lines.append(
            f"| {label}: deterministic (bin centres) | {d['bins']} | {d['rms_rel_s0']:.2e} | {d['rms_dolp']:.2e} "
            f"| {d['rms_aop_deg']:.2e} |"
        )
        for n, e in a["monte_carlo"].items():
            lines.append(
                f"| {label}: Monte Carlo {int(n):,} facets (predicted S0 {e['predicted_rms_rel_s0']:.2f}) | {e['bins']} "
                f"| {e['rms_rel_s0']:.3f} | {e['rms_dolp']:.3f} | {e['rms_aop_deg']:.1f} |"
            )
    for key, e in rep["accuracy"]["sky_map_1deg"].items():
        lines.append(
            f"| sky map 1 deg: {key} | {e['bins']} | {e['rms_rel_s0']:.2e} | {e['rms_dolp']:.2e} | {e['rms_aop_deg']:.2e} |"
        )
    lines += [
        "",
        (
            "| Equal accuracy (RMS rel S0 error) | MC error ~ N^-x, x (last pair) | Facets for det. accuracy "
            "| MC time then s | Det. time s | Speed-up at equal accuracy | Speed-up at equal grid |"
        ),
        "|---|--:|--:|--:|--:|--:|--:|",
    ]
    for label in ("sun", "sun+sky"):
        a = rep["accuracy"][label]
        lines.append(
            f"| {label} | {a['mc_error_exponent_last_pair']:.2f} | {a['equal_accuracy_facets']:.2e} "
            f"| {a['equal_accuracy_mc_time_s']:.2e} | {a['deterministic_time_s']:.3f} "
            f"| {a['speedup_equal_accuracy']:.2e}x | {a['speedup_equal_grid']:.2f}x |"
        )
    lines += harness.target_table(rep["targets"], spec=".3f", column="Result", align="--:")
    m = rep["machine"]
    lines += [
        "",
        (
            f"Machine: {m['cpu_model']}, {m['cpu_count']} cores, numba {m['numba']} with {m['numba_threads']} "
            f"threads, numpy {m['numpy']}, Python {m['python']}."
        ),
        "",
        *[f"- {n}" for n in (*NOTES, *rep["notes"])],
    ]
    return "\n".join(lines)


def main(
    argv: Sequence[str] | None = None,
    *,
    repeat: int | None = None,
    quick: bool = False,
    warmup: int | None = None,
    json_path: Path | None = RESULTS_PATH,
    echo: bool = True,
) -> dict[str, Any]:
    """Run the benchmark, print the markdown report and write the JSON.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH``); ``None`` or empty reads nothing.
    repeat, warmup : int, optional
        Timed and untimed calls per row; default 10 and 1, or 3 and 1 with
        ``quick`` (Monte Carlo rows use half, or a quarter for 400k facets).
    quick : bool
        Fewer calls and coarser subsets, for a fast look.
    json_path : pathlib.Path or None
        Where to write the JSON report; ``None`` writes nothing.
    echo : bool
        Print the markdown report.

    Returns
    -------
    dict
        The report; ``targets`` carry ``passed`` flags.
    """
    o = harness.options(argv, description=__doc__.split("\n\n")[0], counts=COUNTS, repeat=repeat, warmup=warmup,
                        quick=quick, json_path=json_path)
    report = run_benchmark(o.repeat, o.warmup, o.quick)
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:])
