"""Accuracy study: full-resolution demosaicing against bilinear and super-pixel.

Seeded synthetic heliostat scenes (:func:`pihim.render.scenes.edge_scene`:
facets with sharp, partly oblique edges, 1-4 px dark gaps, thin glints,
sub-pixel-accurate edges) are rendered as IMX250MZR mosaics by
:func:`pihim.render.mosaic.mosaic_from_stokes`, once without noise (float
mosaic, no quantisation) and once with realistic noise (12-bit, shot noise
at 2.5 e-/DN, read noise 2 DN). Each route's Stokes image is compared with
the full-resolution ground truth:

``bilinear``
    Per-channel bilinear interpolation (:func:`pihim.camera.demosaic.bilinear`),
    then the ideal pseudo-inverse.
``pihim full``
    ``polar_image(m, demosaic="full")``: the fused numba kernel of
    :func:`pihim.camera.demosaic.full_resolution`.
``super-pixel (nearest)``
    ``polar_image(m, demosaic="superpixel")`` with each super-pixel value
    repeated over its 2x2 pixels: the half-resolution reference.

With ``--alternatives`` the numpy variants that were considered for the
full-resolution route (see ``full_resolution``'s notes) are evaluated too.

Metrics (over the whole image, borders included):

* S0 PSNR in dB, peak = max of the true S0;
* DoLP PSNR in dB, peak 1 (an estimated S0 <= 0 counts as DoLP 0);
* AoP RMSE in degrees, axial difference, on pixels whose true DoLP > 0.1.

Prints a markdown table (mean over the scenes) and writes every number to
``benchmarks/results/demosaic_quality.json``. Run
``python benchmarks/demosaic_quality.py [--quick] [--alternatives]`` or
``python benchmarks/run.py --quality --only demosaic_quality``.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.camera import demosaic
from pihim.camera.layout import IMX250MZR
from pihim.camera.pipeline import polar_image
from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.polarimetry.stokes import aop_deg, aop_difference_deg, dolp
from pihim.render.mosaic import mosaic_from_stokes
from pihim.render.scenes import edge_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

FRAME_SHAPE: tuple[int, int] = (2048, 2448)  # rows, columns of the IMX250MZR
QUICK_SHAPE: tuple[int, int] = (512, 640)
DEFAULT_SEEDS: tuple[int, ...] = (1, 2, 3)
QUICK_SEEDS: tuple[int, ...] = (1, 2)
NOISE = {"read_noise_dn": 2.0, "electrons_per_dn": 2.5, "bit_depth": 12}
AOP_MIN_DOLP = 0.1
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "demosaic_quality.json"

IDEAL = AnalyserMatrix.ideal()
Stokes = NDArray[np.float64]


# -- metrics ---------------------------------------------------------------------------------


def quality(est: Stokes, truth: tuple[NDArray, NDArray, NDArray]) -> dict[str, float]:
    """S0 PSNR (dB), DoLP PSNR (dB) and AoP RMSE (deg) of a (3, H, W) Stokes estimate."""
    s0t, s1t, s2t = truth
    est = np.asarray(est, dtype=np.float64)
    mse_s0 = float(np.mean((est[0] - s0t) ** 2))
    p_true = dolp(s0t, s1t, s2t)
    p_est = np.nan_to_num(dolp(est[0], est[1], est[2]), nan=0.0)
    mse_p = float(np.mean((p_est - p_true) ** 2))
    sel = p_true > AOP_MIN_DOLP
    d = aop_difference_deg(aop_deg(est[1], est[2]), aop_deg(s1t, s2t))[sel]
    return {
        "s0_psnr_db": 10.0 * np.log10(float(s0t.max()) ** 2 / mse_s0),
        "dolp_psnr_db": 10.0 * np.log10(1.0 / mse_p),
        "aop_rmse_deg": float(np.sqrt(np.mean(d**2))),
    }


# -- routes ----------------------------------------------------------------------------------


def route_bilinear(m: NDArray) -> Stokes:
    return IDEAL.stokes(demosaic.bilinear(m, IMX250MZR))


def route_full(m: NDArray) -> Stokes:
    pi = polar_image(m, demosaic="full")
    return np.stack([pi.s0, pi.s1, pi.s2]).astype(np.float64)


def route_superpixel(m: NDArray) -> Stokes:
    pi = polar_image(m, demosaic="superpixel")
    s = np.stack([pi.s0, pi.s1, pi.s2]).astype(np.float64)
    return np.repeat(np.repeat(s, 2, axis=1), 2, axis=2)


ROUTES: dict[str, Callable[[NDArray], Stokes]] = {
    "bilinear": route_bilinear,
    "pihim full": route_full,
    "super-pixel (nearest)": route_superpixel,
}


# -- alternatives considered for the full-resolution route (numpy only) -----------------------


def _variant(
    m: NDArray,
    *,
    adaptive: bool = True,
    domain: str = "difference",
    diagonal: str = "stage2",
    clamp: bool = True,
) -> NDArray[np.float64]:
    """The full-resolution method with one design choice changed; channels (4, H, W).

    ``adaptive=False`` gives every direction the same weight (a linear
    filter); ``domain="ratio"`` makes the one-sided estimates
    ``m[p+d] * 2 m[p] / (m[p] + m[p+2d])`` instead of channel differences;
    ``diagonal="direct"`` estimates the diagonal channel from the four
    diagonal samples (one-sided along the diagonals) instead of from the
    neighbours' stage-1 results; ``clamp=False`` drops the range clamps.
    With the defaults this reproduces :func:`pihim.camera.demosaic.full_resolution`.
    """
    m = np.asarray(m, dtype=np.float64)
    h, w = m.shape
    x = np.pad(m, 3, mode="reflect")

    def s(di: int, dj: int) -> NDArray[np.float64]:
        return x[3 + di : 3 + di + h, 3 + dj : 3 + dj + w]

    c = s(0, 0)

    def grad(di: int, dj: int) -> NDArray[np.float64]:
        ei, ej = abs(dj), abs(di)
        if ei == 0 and ej == 0 or (di and dj):  # diagonal direction: no perpendicular terms
            return np.abs(c - s(2 * di, 2 * dj)) + 0.5 * np.abs(s(di, dj) - s(3 * di, 3 * dj))
        return (
            np.abs(c - s(2 * di, 2 * dj))
            + 0.5 * np.abs(s(di, dj) - s(3 * di, 3 * dj))
            + np.abs(s(ei, ej) - s(ei + 2 * di, ej + 2 * dj))
            + np.abs(s(-ei, -ej) - s(-ei + 2 * di, -ej + 2 * dj))
        )

    def weight(di: int, dj: int) -> NDArray[np.float64]:
        return 1.0 / (demosaic.FULLRES_GRAD_EPS + grad(di, dj)) if adaptive else np.ones_like(c)

    def estimate(di: int, dj: int) -> NDArray[np.float64]:
        if domain == "ratio":
            return s(di, dj) * (2.0 * c + 1.0) / (c + s(2 * di, 2 * dj) + 1.0)
        return s(di, dj) + 0.5 * (c - s(2 * di, 2 * dj))

    def fuse(dirs: Sequence[tuple[int, int]], values: Sequence[NDArray] | None = None) -> NDArray[np.float64]:
        ws = [weight(*d) for d in dirs]
        vals = values if values is not None else [estimate(*d) for d in dirs]
        return sum(wi * vi for wi, vi in zip(ws, vals, strict=True)) / sum(ws)

    def clamped(v: NDArray, dirs: Sequence[tuple[int, int]]) -> NDArray[np.float64]:
        if not clamp:
            return v
        samples = np.stack([s(*d) for d in dirs])
        return np.clip(v, samples.min(axis=0), samples.max(axis=0))

    hv = clamped(fuse(((0, -1), (0, 1))), ((0, -1), (0, 1)))
    vv = clamped(fuse(((-1, 0), (1, 0))), ((-1, 0), (1, 0)))
    diag = ((-1, -1), (-1, 1), (1, -1), (1, 1))
    if diagonal == "direct":
        dv = fuse(diag)
    else:
        hp, vp = np.pad(hv, 1, mode="reflect"), np.pad(vv, 1, mode="reflect")
        dirs = ((0, -1), (0, 1), (-1, 0), (1, 0))
        vals = []
        for di, dj in dirs:
            other = vp if di == 0 else hp
            own = hv if di == 0 else vv
            nb = other[1 + di : 1 + di + h, 1 + dj : 1 + dj + w]
            if domain == "ratio":
                vals.append(own * (nb + 1.0) / (s(di, dj) + 1.0))
            else:
                vals.append(own + nb - s(di, dj))
        dv = fuse(dirs, vals)
    dv = clamped(dv, diag)
    return _assemble(c, hv, vv, dv)


def _assemble(*roles: NDArray[np.float64]) -> NDArray[np.float64]:
    """Own/H/V/D role images -> channels 0/45/90/135 for the IMX250MZR layout."""
    h, w = roles[0].shape
    pos = 2 * (np.arange(h)[:, None] % 2) + (np.arange(w)[None, :] % 2)
    ch_of_pos = np.empty(4, dtype=np.intp)
    for k, (r, c) in enumerate(IMX250MZR.channel_positions):
        ch_of_pos[2 * r + c] = k
    out = np.empty((4, h, w))
    for role, val in enumerate(roles):
        ch = ch_of_pos[pos ^ role]
        for k in range(4):
            out[k][ch == k] = val[ch == k]
    return out


def _binomial_difference(m: NDArray) -> NDArray[np.float64]:
    """Linear difference interpolation against a 3x3-binomial S0/2 guide (no clamps)."""
    import cv2

    m = np.asarray(m, dtype=np.float64)
    kern = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]]) / 16.0
    guide = cv2.filter2D(m, -1, kern, borderType=cv2.BORDER_REFLECT_101)
    return demosaic.bilinear(m - guide, IMX250MZR) + guide[None]


ALTERNATIVES: dict[str, Callable[[NDArray], Stokes]] = {
    "alt: binomial-guide difference (linear)": lambda m: IDEAL.stokes(_binomial_difference(m)),
    "alt: Newton difference, equal weights": lambda m: IDEAL.stokes(_variant(m, adaptive=False)),
    "alt: ratio domain": lambda m: IDEAL.stokes(_variant(m, domain="ratio")),
    "alt: diagonal channel direct": lambda m: IDEAL.stokes(_variant(m, diagonal="direct")),
    "alt: no range clamps": lambda m: IDEAL.stokes(_variant(m, clamp=False)),
}


# -- study -----------------------------------------------------------------------------------


def render(shape: tuple[int, int], seed: int, noisy: bool) -> tuple[NDArray, tuple[NDArray, NDArray, NDArray]]:
    """Ground truth and mosaic of one scene."""
    truth = edge_scene(shape, seed)
    if noisy:
        m = mosaic_from_stokes(*truth, rng=1000 + seed, **NOISE)
    else:
        m = mosaic_from_stokes(*truth, bit_depth=None)
    return m, truth


def study(
    shape: tuple[int, int], seeds: Sequence[int], alternatives: bool = False
) -> dict[str, dict[str, list[dict[str, float]]]]:
    """Per-condition, per-route list of per-scene metrics."""
    routes = dict(ROUTES)
    if alternatives:
        routes.update(ALTERNATIVES)
    out: dict[str, dict[str, list[dict[str, float]]]] = {}
    for noisy in (False, True):
        cond = "noisy" if noisy else "clean"
        out[cond] = {name: [] for name in routes}
        for seed in seeds:
            m, truth = render(shape, seed, noisy)
            for name, fn in routes.items():
                out[cond][name].append({"seed": seed, **quality(fn(m), truth)})
    return out


def _mean(rows: list[dict[str, float]], key: str) -> float:
    return float(np.mean([r[key] for r in rows]))


def markdown(results: dict[str, dict[str, list[dict[str, float]]]]) -> str:
    """Table of the means over the scenes."""
    conds = list(results)
    head = "| Route | " + " | ".join(
        f"{c} S0 PSNR dB | {c} DoLP PSNR dB | {c} AoP RMSE deg" for c in conds
    ) + " |"
    sep = "|---|" + "---:|" * (3 * len(conds))
    lines = [head, sep]
    for name in results[conds[0]]:
        cells = []
        for c in conds:
            rows = results[c][name]
            cells += [
                f"{_mean(rows, 's0_psnr_db'):.2f}",
                f"{_mean(rows, 'dolp_psnr_db'):.2f}",
                f"{_mean(rows, 'aop_rmse_deg'):.2f}",
            ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, *, quick: bool | None = None) -> dict[str, Any]:
    """Run the study, print the table, write the JSON; return the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SHAPE[1]}x{QUICK_SHAPE[0]} scenes, 2 seeds")
    parser.add_argument("--seeds", type=int, nargs="+", help="scene seeds (default 1 2 3)")
    parser.add_argument("--shape", type=int, nargs=2, metavar=("ROWS", "COLS"), help="scene size")
    parser.add_argument("--alternatives", action="store_true", help="also evaluate the alternatives considered")
    parser.add_argument("--out", type=Path, default=RESULTS_PATH, help="JSON output path")
    args = parser.parse_args(argv)
    quick = bool(quick or args.quick)
    shape = tuple(args.shape) if args.shape else (QUICK_SHAPE if quick else FRAME_SHAPE)
    seeds = tuple(args.seeds) if args.seeds else (QUICK_SEEDS if quick else DEFAULT_SEEDS)

    start = time.perf_counter()
    results = study(shape, seeds, alternatives=args.alternatives)
    elapsed = time.perf_counter() - start

    print(f"Scenes: edge_scene {shape[1]}x{shape[0]} (WxH), seeds {list(seeds)}; "
          f"noisy = 12-bit, shot noise {NOISE['electrons_per_dn']} e-/DN, read noise {NOISE['read_noise_dn']} DN.")
    print(f"AoP RMSE on pixels with true DoLP > {AOP_MIN_DOLP}; means over the scenes.\n")
    print(markdown(results))

    beats = all(
        f["s0_psnr_db"] > b["s0_psnr_db"]
        and f["dolp_psnr_db"] > b["dolp_psnr_db"]
        and f["aop_rmse_deg"] < b["aop_rmse_deg"]
        for cond in results.values()
        for f, b in zip(cond["pihim full"], cond["bilinear"], strict=True)
    )
    report: dict[str, Any] = {
        "benchmark": "demosaic_quality",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "numpy": np.__version__},
        "shape": list(shape),
        "seeds": list(seeds),
        "noise": NOISE,
        "aop_min_true_dolp": AOP_MIN_DOLP,
        "seconds": elapsed,
        "per_scene": results,
        "mean": {
            cond: {
                name: {k: _mean(rows, k) for k in ("s0_psnr_db", "dolp_psnr_db", "aop_rmse_deg")}
                for name, rows in per.items()
            }
            for cond, per in results.items()
        },
        "targets": [
            {"target": "pihim full beats bilinear in S0 PSNR, DoLP PSNR and AoP RMSE on every scene", "passed": beats}
        ],
    }
    harness.write_json(report, args.out)
    print(f"\nfull beats bilinear on every scene and metric: {beats}; JSON: {args.out} ({elapsed:.0f} s)")
    return report


if __name__ == "__main__":
    main()
