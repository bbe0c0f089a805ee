"""The planner's compiled inner loops (:mod:`pihim.planning._kernels`) against plain-loop oracles."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pihim.planning import _kernels
from pihim.planning.facet_captures import _cone_intervals, _polygon_terms, cone_interval

RNG = np.random.default_rng(20261126)


def _random_quads(rng, shape):
    """Random planar convex quads (shape..., 4, 3): rotated, scaled squares."""
    square = np.array([[1.0, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]])
    out = np.empty((*shape, 4, 3))
    for idx in np.ndindex(*shape):
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        out[idx] = square @ rot.T * rng.uniform(0.5, 3.0) + rng.normal(size=3) * 4
    return out


@pytest.mark.parametrize("negative", [False, True])
def test_cone_intervals_agree_with_the_closed_form_one_at_a_time(negative):
    rng = np.random.default_rng(11)
    B, I, J = 4, 8, 5
    quads = _random_quads(rng, (B, J))
    q = rng.normal(size=(B, I, 3)) * 3
    a = rng.normal(size=(B, I, 3)) * 6
    e = rng.normal(size=(B, I, 3))
    idx = np.tile(np.arange(J), (B, 1))
    idx[1, 2] = -1  # padding
    window = (np.full(B, -8.0), np.full(B, 8.0))
    lo, hi = _cone_intervals(q, a, e, _polygon_terms(quads), idx, window, negative)
    met = missed = 0
    for b, i, j in itertools.product(range(B), range(I), range(J)):
        got = (lo[b, i, j], hi[b, i, j])
        if idx[b, j] < 0:
            assert got == (math.inf, -math.inf)
            continue
        want_lo, want_hi = cone_interval(q[b, i], quads[b, j], a[b, i], e[b, i], negative=negative)
        if want_lo > want_hi:  # misses the cone: an empty interval
            assert got[0] > got[1]
            missed += 1
            continue
        if want_lo > 8.0 or want_hi < -8.0:  # misses the window: marked empty
            assert got == (math.inf, -math.inf)
            missed += 1
            continue
        met += 1
        assert got == pytest.approx((float(want_lo), float(want_hi)), rel=1e-9, abs=1e-9)
    assert met >= 5 and missed >= 5  # both outcomes exercised


def _facet_grid_oracle(s, valid, r_lo, r_hi, back, tgt, b_lo, b_hi, f_lo, f_hi, q, cam, fwd, right, down,
                       n_f, tx, ty):
    B, G, A = fwd.shape[:3]
    n_i = q.shape[1]
    n_s = n_i // n_f
    good = np.zeros((B, G, A, n_f), bool)
    target = np.full((B, G, A, n_f), -1)
    for b, g in itertools.product(range(B), range(G)):
        sg = s[b, g]
        vis = []
        for i in range(n_i):
            inside = [j for j in range(r_lo.shape[2]) if r_lo[b, i, j] <= sg <= r_hi[b, i, j]]
            ok = (valid[b, g] and f_lo[b, i] < sg < f_hi[b, i] and bool(inside) and back[b, i, inside[0]]
                  and not any(b_lo[b, i, j] <= sg <= b_hi[b, i, j] for j in range(b_lo.shape[2])))
            vis.append(tgt[b, inside[0]] if ok else -1)
        for a, f in itertools.product(range(A), range(n_f)):
            for k in range(n_s):
                i = f * n_s + k
                v = q[b, i] - cam[b, g]
                z, x, y = fwd[b, g, a] @ v, right[b, g, a] @ v, down[b, g, a] @ v
                if vis[i] >= 0 and z > 0 and abs(x) <= tx * z and abs(y) <= ty * z:
                    good[b, g, a, f], target[b, g, a, f] = True, vis[i]
                    break
    return good, target


def test_facet_grid_agrees_with_plain_loops():
    B, G, A, n_f, n_s, J, Jb = 2, 5, 3, 4, 3, 4, 2
    n_i = n_f * n_s
    s = np.sort(RNG.uniform(-5, 5, size=(B, G)), axis=1)
    valid = RNG.random((B, G)) > 0.2

    def intervals(j):
        c = RNG.uniform(-5, 5, size=(B, n_i, j))
        w = RNG.uniform(0, 4, size=(B, n_i, j))
        lo, hi = c - w, c + w
        miss = RNG.random((B, n_i, j)) < 0.3
        return np.where(miss, np.inf, lo), np.where(miss, -np.inf, hi)

    r_lo, r_hi = intervals(J)
    b_lo, b_hi = intervals(Jb)
    back = RNG.random((B, n_i, J)) > 0.3
    tgt = RNG.integers(0, 50, size=(B, J))
    f_lo, f_hi = RNG.uniform(-8, 0, size=(B, n_i)), RNG.uniform(0, 8, size=(B, n_i))
    q = RNG.normal(size=(B, n_i, 3)) * 2
    cam = RNG.normal(size=(B, G, 3)) * 2 + np.array([0.0, 0.0, 10.0])
    axes = np.linalg.qr(RNG.normal(size=(B * G * A, 3, 3)))[0].reshape(B, G, A, 3, 3)
    fwd, right, down = (np.ascontiguousarray(axes[..., k]) for k in range(3))
    args = (s, valid, r_lo, r_hi, back, tgt, b_lo, b_hi, f_lo, f_hi, q, cam, fwd, right, down, n_f, 1.2, 1.0)
    good, target = _kernels.facet_grid(*args)
    want_good, want_target = _facet_grid_oracle(*args)
    assert want_good.any() and not want_good.all()
    np.testing.assert_array_equal(good, want_good)
    np.testing.assert_array_equal(target, want_target)


def test_first_hits_in_rows_agrees_with_plain_loops():
    """Each ray against its own row only (rows padded, in any order); equal distances: the least index."""
    rng = np.random.default_rng(8)
    n_m, n_r = 24, 300
    centres = rng.uniform(-10, 10, size=(n_m, 3))
    rot = np.linalg.qr(rng.normal(size=(n_m, 3, 3)))[0]
    centres[5], rot[5] = centres[17], rot[17]  # two mirrors in one place: a tie, 5 must win where both are tested
    x, y, normals = (np.ascontiguousarray(rot[:, :, k]) for k in range(3))
    table = np.full((8, 10), -1)
    for k in range(8):
        members = rng.choice(n_m, size=rng.integers(0, 11), replace=False)
        table[k, :len(members)] = members[::-1] if k % 2 else members
    table[0, :3] = (17, 3, 5)  # the tie in reversed order
    row = rng.integers(0, 8, n_r)
    row[:40] = 0
    p0 = rng.uniform(-15, 15, size=(n_r, 3))
    aim = centres[rng.integers(0, n_m, n_r)] + rng.normal(size=(n_r, 3))  # most rays pass near a mirror
    aim[:40] = centres[17] + rng.normal(scale=0.2, size=(40, 3))
    d = (aim - p0) / np.linalg.norm(aim - p0, axis=1, keepdims=True)
    t_max = rng.uniform(5, 40, n_r)
    hw, hh = 1.5, 1.0
    unskipped = _kernels.first_hits_in_rows(p0, d, table, row, np.full(n_r, -1), t_max, normals, centres, x, y,
                                            hw, hh)
    skip = np.where(rng.random(n_r) < 0.3, rng.integers(0, n_m, n_r), -1)
    skip[::4] = unskipped[::4]  # a quarter of the rays skip the mirror they would meet first
    got = _kernels.first_hits_in_rows(p0, d, table, row, skip, t_max, normals, centres, x, y, hw, hh)
    want = np.full(n_r, -1)
    for r in range(n_r):
        best = math.inf
        for m in sorted(int(v) for v in table[row[r]] if v >= 0):
            den = d[r] @ normals[m]
            if m == skip[r] or den == 0:
                continue
            t = (centres[m] - p0[r]) @ normals[m] / den
            hit = p0[r] + t * d[r] - centres[m]
            if 1e-9 < t < min(t_max[r], best) and abs(hit @ x[m]) <= hw and abs(hit @ y[m]) <= hh:
                best, want[r] = t, m
    assert (want >= 0).sum() > 20 and (want < 0).sum() > 20
    assert (want == 5).sum() >= 5  # the tie was met
    assert ((unskipped[::4] >= 0) & (want[::4] != unskipped[::4])).sum() >= 5  # skipping changed the answer
    np.testing.assert_array_equal(got, want)


def _first_hits_oracle(p0, p1, exclude, centres, normals, x, y, hw, hh, eps):
    """Every segment against every mirror, plain loops."""
    out = np.full(len(p0), -1)
    for i in range(len(p0)):
        best = math.inf
        d = p1[i] - p0[i]
        for j in range(len(centres)):
            den = d @ normals[j]
            if j in exclude[i] or den == 0:
                continue
            t = (centres[j] - p0[i]) @ normals[j] / den
            q = p0[i] + t * d - centres[j]
            if np.isfinite(t) and eps < t < 1 - eps and t < best and abs(q @ x[j]) <= hw and abs(q @ y[j]) <= hh:
                best, out[i] = t, j
    return out


def _grid(centres, cell, lo=None, hi=None):
    """A grid as pihim.planning.sightlines.MirrorIndex lays it out, written out for a test: over ``lo``-``hi``
    (default all the centres), a centre beyond it in the nearest edge cell."""
    lo = centres[:, :2].min(axis=0) if lo is None else np.asarray(lo, float)
    hi = centres[:, :2].max(axis=0) if hi is None else np.asarray(hi, float)
    n_x, n_y = (int(v) + 1 for v in np.floor((hi - lo) / cell))
    cx = np.clip(np.floor((centres[:, 0] - lo[0]) / cell), 0, n_x - 1)
    cy = np.clip(np.floor((centres[:, 1] - lo[1]) / cell), 0, n_y - 1)
    key = (cx * n_y + cy).astype(np.int64)
    order = np.argsort(key, kind="stable")
    return order, np.searchsorted(key[order], np.arange(n_x * n_y + 1)).astype(np.int64), lo[0], lo[1], cell, n_x, n_y


@pytest.mark.parametrize("cell, bounds", [
    (0.7, None), (3.0, None), (50.0, None),  # cells smaller than, about, and larger than a mirror
    (3.0, ((-5.0, -8.0), (6.0, 4.0))),  # a grid over part of the field: most centres in its edge cells
])
def test_grid_first_hits_agrees_with_every_segment_against_every_mirror(cell, bounds):
    rng = np.random.default_rng(7)
    n_m, n_r, hw, hh = 60, 400, 1.5, 1.0
    centres = np.column_stack([rng.uniform(-20, 20, (n_m, 2)), rng.uniform(1, 4, n_m)])
    rot = np.linalg.qr(rng.normal(size=(n_m, 3, 3)))[0]
    x, y, normals = (np.ascontiguousarray(rot[:, :, k]) for k in range(3))
    p0 = np.column_stack([rng.uniform(-30, 30, (n_r, 2)), rng.uniform(0, 25, n_r)])
    aim = centres[rng.integers(0, n_m, n_r)] + rng.normal(size=(n_r, 3))  # most segments pass near a mirror
    p1 = p0 + (aim - p0) * rng.uniform(0.5, 3.0, (n_r, 1))  # some stop short of it
    p1[:10] = p0[:10] + [0.0, 0.0, 1e-3]  # short segments
    p0[10:14, 0] = [np.nan, np.inf, -np.inf, 1e12]  # not finite: meet nothing; far: every cell scanned
    p0[14:20] += [500.0, 0.0, 0.0]  # starting far outside the grid
    exclude = np.where(rng.random((n_r, 2)) < 0.2, rng.integers(0, n_m, (n_r, 2)), -1)
    args = (centres, normals, x, y, hw, hh, math.hypot(hw, hh), 1e-6)
    got = _kernels.grid_first_hits(p0, p1, exclude, *_grid(centres, cell, *(bounds or ())), *args)
    with np.errstate(all="ignore"):
        want = _first_hits_oracle(p0, p1, exclude, centres, normals, x, y, hw, hh, 1e-6)
    assert (want >= 0).sum() > 50 and (want < 0).sum() > 50
    assert np.all(got[10:13] == -1)
    np.testing.assert_array_equal(got, want)


def _path_clear(p, r, keep):
    return not _kernels.crosses(p[0], p[1], r[0], r[1], keep)


def test_detour_is_the_shortest_clear_path_around_the_rectangle():
    keep = np.array([-5.0, -3.0, 5.0, 3.0, 40.0])
    corners = [np.array(c) for c in ((-5.0, -3.0), (5.0, -3.0), (5.0, 3.0), (-5.0, 3.0))]
    crossed = 0
    for _ in range(300):
        a, b = RNG.uniform(-15, 15, size=2), RNG.uniform(-15, 15, size=2)
        if (np.abs(a) < [5, 3]).all() or (np.abs(b) < [5, 3]).all():
            continue
        path, n = _kernels.detour(a[0], a[1], b[0], b[1], keep)
        pts = [a, *path[:n], b]
        assert all(_path_clear(p, r, keep) for p, r in zip(pts[:-1], pts[1:], strict=True))
        length = sum(float(np.linalg.norm(r - p)) for p, r in zip(pts[:-1], pts[1:], strict=True))
        best = math.inf  # every sequence of distinct corners whose legs stay clear of the rectangle
        for k in range(5):
            for seq in itertools.permutations(corners, k):
                route = [a, *seq, b]
                if all(_path_clear(p, r, keep) for p, r in zip(route[:-1], route[1:], strict=True)):
                    best = min(best, sum(float(np.linalg.norm(r - p)) for p, r in
                                         zip(route[:-1], route[1:], strict=True)))
        assert length == pytest.approx(best, rel=1e-12)
        crossed += n > 0
        # straight(): the same length plus the climb, and only below the top
        za, zb = RNG.uniform(0, 30, size=2)
        assert _kernels.straight(a[0], a[1], za, b[0], b[1], zb, keep) == pytest.approx(length + abs(zb - za),
                                                                                rel=1e-12)
        high = _kernels.straight(a[0], a[1], 50.0, b[0], b[1], 45.0, keep)
        assert high == pytest.approx(math.hypot(*(b - a)) + 5.0, rel=1e-12)
    assert crossed > 50


def test_transit_is_symmetric_and_charges_turns():
    pts = np.array([[0.0, 0, 10], [0, 20, 10], [10, 20, 12], [10, 0, 12]])
    out = np.array([[0.0, -1], [0, 1], [0, 1], [0, -1]])  # pass 0 runs north, pass 1 south
    none = np.empty(0)
    cos30 = math.cos(math.radians(30.0))
    for e1, e2 in itertools.product(range(4), repeat=2):
        if e1 == e2:
            continue
        plain = _kernels.transit(pts, out, e1, e2, none, 0.0, cos30)
        assert plain == _kernels.transit(pts, out, e2, e1, none, 0.0, cos30)
        assert plain == pytest.approx(math.hypot(*(pts[e2, :2] - pts[e1, :2])) + abs(pts[e2, 2] - pts[e1, 2]))
    # north end of pass 0 (row 1) -> north end of pass 1 (row 2): east across, two 90 deg turns
    assert _kernels.transit(pts, out, 1, 2, none, 7.0, cos30) == pytest.approx(10.0 + 2.0 + 14.0)
    # north end of pass 0 -> south end of pass 1: out north, leg south-east (> 30 deg), in north (> 30 deg)
    assert _kernels.transit(pts, out, 1, 3, none, 7.0, cos30) == pytest.approx(math.hypot(10, 20) + 2.0 + 14.0)


def _leg(pts, out, e1, e2):
    if e1 < 0 or e2 < 0:
        return 0.0
    return _kernels.transit(pts, out, e1, e2, np.empty(0), 0.0, 0.5)


def _no_marks(n):
    """Fresh don't-look marks: every search is made."""
    return np.zeros(n, np.int64), np.zeros((4, n), np.int64), np.ones(1, np.int64)


def test_improve_sweep_leaves_no_improving_reversal_or_move():
    n = 14
    pts = np.repeat(RNG.uniform(0, 100, size=(n, 1, 3)), 2, axis=1).reshape(2 * n, 3)
    pts[1::2, :2] += RNG.normal(size=(n, 2)) * 5  # each pass a short segment
    out = np.zeros((2 * n, 2))
    order = RNG.permutation(n).astype(np.int64)
    dirs = np.zeros(n, np.int64)
    start = order.copy()

    def length(o, dr):
        return sum(_leg(pts, out, 2 * o[i] + 1 - dr[i], 2 * o[i + 1] + dr[i + 1]) for i in range(n - 1))

    before = length(order, dirs)
    for _ in range(50):
        if not _kernels.improve_sweep(order, dirs, pts, out, np.empty(0), 0.0, 0.5, 0, n - 1, n, *_no_marks(n)):
            break
    assert sorted(order.tolist()) == sorted(start.tolist())  # a permutation: every pass once
    after = length(order, dirs)
    assert after < before
    # converged: no segment reversal (2-opt) shortens the path
    for i, j in itertools.combinations(range(n), 2):
        o2, d2 = order.copy(), dirs.copy()
        o2[i:j + 1], d2[i:j + 1] = o2[i:j + 1][::-1].copy(), 1 - d2[i:j + 1][::-1]
        assert length(o2, d2) >= after - 1e-6


@pytest.mark.parametrize("pinned", [False, True])
def test_improve_sweep_dont_look_marks_change_nothing(pinned):
    """Kept across sweeps, the don't-look marks skip searches that would find nothing: the same moves as
    searching everywhere every sweep, on random orders with turn costs and a keep-out in the way, small windows
    (where a mark's reach ends matters most)."""
    n = 80
    for seed in range(12):
        rng = np.random.default_rng(seed)
        pts = np.repeat(rng.uniform(0, 400, size=(n, 1, 3)), 2, axis=1).reshape(2 * n, 3)
        pts[:, 2] = rng.choice([20.0, 25.0], size=2 * n)
        pts[1::2, :2] += rng.normal(size=(n, 2)) * 20
        out = rng.normal(size=(2 * n, 2))
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        keep = np.array([180.0, 180.0, 220.0, 220.0, 60.0])
        lo, hi = (1, n - 2) if pinned else (0, n - 1)
        window = 2 + seed % 4
        start = rng.permutation(n).astype(np.int64)
        runs = []
        for marks in (None, _no_marks(n)):
            order, dirs = start.copy(), np.zeros(n, np.int64)
            flags = []
            for _ in range(10):
                m = _no_marks(n) if marks is None else marks
                flags.append(_kernels.improve_sweep(order, dirs, pts, out, keep, 10.0, 0.866, lo, hi, window, *m))
            runs.append((order.tolist(), dirs.tolist(), flags))
        assert runs[0] == runs[1], seed
        assert runs[0][2][0]  # it moved


def _greedy_oracle(good, target, kk, used, passes, commit, max_captures, min_gain):
    """Plain loops: rounds over the instances, each taking its best (position, aim) by facets added."""
    B, G, A, F = good.shape
    tie = np.abs(np.arange(G) - G // 2)[:, None] * 1e-3 + np.arange(A)[None, :] * 1e-5
    cov = np.zeros((B, F), bool)
    used = {k: set(v) for k, v in used.items()}
    mine = [set() for _ in range(B)]
    active = [True] * B
    picks = [[] for _ in range(B)]
    for _ in range(max_captures):
        for b in range(B):
            if not active[b]:
                continue
            taken = used.get(passes[b], set()) | mine[b]
            best = None
            for g, a in itertools.product(range(G), range(A)):
                gain = -1.0 if kk[b, g] in taken else float(np.sum(good[b, g, a] & ~cov[b]))
                if best is None or gain - tie[g, a] > best[0]:
                    best = (gain - tie[g, a], g, a, gain)
            _, g, a, gain = best
            if gain < min_gain:
                active[b] = False
                continue
            new = good[b, g, a] & ~cov[b]
            shown = sorted(int(t) for t in target[b, g, a][new] if t >= 0)
            top = max(shown, key=lambda t: (shown.count(t), -t)) if shown else -1
            picks[b].append((g, a, new.tolist(), top))
            cov[b] |= new
            mine[b].add(int(kk[b, g]))
            if commit:
                used.setdefault(passes[b], set()).add(int(kk[b, g]))
    return picks


@pytest.mark.parametrize("commit", [True, False])
def test_greedy_captures_agree_with_plain_loops(commit):
    from pihim.planning.facet_captures import FacetCaptureSettings, _greedy, _Instance

    rng = np.random.default_rng(5)
    B, G, A, F = 5, 7, 3, 12
    good = rng.random((B, G, A, F)) < 0.35
    target = np.where(good, rng.integers(0, 4, size=(B, G, A, F)), -1)
    passes = [0, 0, 1, 0, 2]  # three instances on one pass line: they share its grid positions
    k0 = np.array([0, 2, 5, 3, 0])
    kk = k0[:, None] + np.arange(G)[None, :]
    used = {0: {4}, 2: {1, 2}}
    st = FacetCaptureSettings(max_captures=3, min_gain=2)
    inst = [_Instance(hua=b, pass_k=p, s0=0.0) for b, p in enumerate(passes)]
    want = _greedy_oracle(good, target, kk, used, passes, commit, st.max_captures, st.min_gain)
    mutable = {k: set(v) for k, v in used.items()}
    got = _greedy({"good": good, "target": target, "k": kk}, inst, mutable, st, commit=commit)
    assert [[(g, a, m.tolist(), t) for g, a, m, t in pk] for pk in got] == want
    assert sum(len(pk) for pk in want) >= 8
    assert mutable == ({k: set(v) for k, v in used.items()} if not commit else
                       {p: used.get(p, set()) | {int(kk[b, g]) for b in range(B) if passes[b] == p
                                                 for g, _, _, _ in want[b]} for p in set(passes) | set(used)})


def test_row_modes_is_the_most_frequent_value_least_among_equals():
    rng = np.random.default_rng(2)
    rows = np.where(rng.random((500, 9)) < 0.4, -1, rng.integers(0, 5, size=(500, 9)))
    rows[0] = -1  # nothing shown
    got = _kernels.row_modes(rows)
    for r, row in enumerate(rows.tolist()):
        vals = [v for v in row if v >= 0]
        assert got[r] == (min(set(vals), key=lambda v: (-vals.count(v), v)) if vals else -1)


def _segments_hit_box_numpy(p0, p1, lo, hi):
    """The slab test in numpy (the planner's code before the compiled kernel)."""
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - p0) * inv
        t2 = (hi - p0) * inv
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    tmax = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2))
    par = d == 0  # parallel components: inside the slab or not
    inside_slab = (p0 >= lo) & (p0 <= hi)
    tmin = np.where(par, np.where(inside_slab, -np.inf, np.inf), tmin)
    tmax = np.where(par, np.where(inside_slab, np.inf, -np.inf), tmax)
    enter = tmin.max(axis=1)
    leave = tmax.min(axis=1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)


def test_segments_hit_box_is_the_numpy_slab_test_with_its_edge_cases():
    """The compiled slab test against the numpy one on random segments, segments parallel to a slab (inside and
    outside it), degenerate (zero-length) segments, segments starting or ending on a face, subnormal components
    and NaN coordinates; and against geometry: a segment through the box's centre hits, one beside it misses."""
    from pihim.planning.sightlines import segments_hit_box

    rng = np.random.default_rng(5)
    lo, hi = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 3.0])
    p0 = rng.uniform(-4, 4, size=(4000, 3))
    p1 = rng.uniform(-4, 4, size=(4000, 3))
    p1[:500, 0] = p0[:500, 0]  # parallel to the x slabs, inside or outside them
    p1[500:700] = p0[500:700]  # zero length
    p0[700:800, 2] = 3.0  # starting on the top face
    p1[800:900, 0] = -1.0  # ending on a side face
    p1[900:950, 1] = p0[900:950, 1] + 5e-324  # subnormal direction component
    p0[950:960, 0] = np.nan
    p1[960:970, 2] = np.nan
    p0[970:975] = [[0.0, 2.0, 1.0]]  # on the y = hi face, moving along it
    p1[970:975] = [[0.5, 2.0, 2.0]]
    got = segments_hit_box(p0, p1, lo, hi)
    want = _segments_hit_box_numpy(p0, p1, lo, hi)
    np.testing.assert_array_equal(got, want)
    assert 0.2 < got.mean() < 0.8 and got[970:975].all()  # (a NaN slab is ignored, as in numpy)
    centre, beside = np.array([[0.0, 0.0, 1.5]]), np.array([[5.0, 0.0, 1.5]])
    assert segments_hit_box(centre - [[3.0, 1.0, 0.5]], centre + [[3.0, 1.0, 0.5]], lo, hi)[0]
    assert not segments_hit_box(beside - [[0.0, 3.0, 0.5]], beside + [[0.0, 3.0, 0.5]], lo, hi)[0]


def test_count_in_view_is_in_fov_summed():
    """The fused count of the planner's line settings against the public steps it replaces: the gaze at each
    HUA's centre, its camera frame, the field-of-view test of the HUA's facet centres, summed."""
    from pihim.camera import CameraModel
    from pihim.planning.sightlines import camera_frame, gaze_angles, in_fov

    rng = np.random.default_rng(5)
    n_h, k, p = 30, 25, 4000
    centres = rng.uniform(-60.0, 60.0, (n_h, 3)) * [1.0, 1.0, 0.05] + [0.0, 0.0, 5.0]
    facets = centres[:, None, :] + rng.normal(scale=3.0, size=(n_h, k, 3))
    hua = rng.integers(0, n_h, p)
    cam = centres[hua] + rng.normal(scale=[25.0, 25.0, 10.0], size=(p, 3)) + [0.0, 0.0, 15.0]
    cam[:5] = centres[hua[:5]] + [0.0, 0.0, 20.0]  # straight above: heading 0 by convention
    camera = CameraModel()
    tx = 0.5 * camera.width_px / camera.focal_length_px
    ty = 0.5 * camera.height_px / camera.focal_length_px
    head, pitch = gaze_angles(cam, centres[hua])
    r, dn, f = camera_frame(head, pitch)
    got = _kernels.count_in_view(facets, hua, cam, r, dn, f, tx, ty)
    want = in_fov(facets[hua], cam, head, pitch, camera).sum(axis=-1)
    np.testing.assert_array_equal(got, want)
    assert 0 < want.mean() < k and (want == 0).any() and (want == k).any()  # partial, none and all in view


@pytest.mark.parametrize(("n_lines", "reach"), [(0, 15.0), (1, 15.0), (300, 15.0), (300, 1e4)])
def test_lines_near_is_the_numpy_test_to_the_last_bit(n_lines, reach):
    """The facet captures' rescue (every HUA to every flown line) against the numpy expression it replaces:
    the same lines in the same order and bit-identical positions along them, a point exactly ``reach`` away
    included; with a reach over the whole area every point meets every line and the buffer has to grow."""
    rng = np.random.default_rng(11)
    theta = rng.uniform(0.0, 2.0 * np.pi, n_lines)
    e = np.column_stack([np.sin(theta), np.cos(theta)])
    a = rng.uniform(-500.0, 500.0, (n_lines, 2))
    pts = rng.uniform(-600.0, 600.0, (400, 2))
    if n_lines:  # on a line's edge: exactly reach to its right (axis-aligned, integers: no rounding)
        a[0], e[0] = (10.0, 20.0), (0.0, 1.0)
        pts[0] = (10.0 + reach, 55.0)
        pts[1:60] = a[-1] + rng.normal(scale=3.0, size=(59, 2))  # crowded near one line
        if n_lines > 1:  # on a line along -x through a: rx = +0, ry * e_y = -0.0; np.sum gives +0.0, not -0.0
            a[1], e[1] = (0.0, 0.0), (-1.0, 0.0)
            pts[60] = (0.0, -5.0)
    start, idx, along = _kernels.lines_near(pts, a, e, reach)
    assert start.shape == (len(pts) + 1,) and start[0] == 0 and start[-1] == len(idx) == len(along)
    for h in range(len(pts)):
        rel = pts[h, None, :] - a
        j = np.flatnonzero(np.abs(rel[:, 0] * e[:, 1] - rel[:, 1] * e[:, 0]) <= reach)
        np.testing.assert_array_equal(idx[start[h]:start[h + 1]], j)
        assert along[start[h]:start[h + 1]].tobytes() == np.sum(rel[j] * e[j], axis=1).tobytes()
    if n_lines:
        assert 0 in idx[start[0]:start[1]].tolist()  # the point on the edge counts
        assert all(n_lines - 1 in idx[start[h]:start[h + 1]].tolist() for h in range(1, 60))
    if n_lines > 1:
        k = start[60] + idx[start[60]:start[61]].tolist().index(1)
        assert along[k] == 0.0 and math.copysign(1.0, along[k]) == 1.0  # +0.0, as the numpy sum
    if reach > 1e3:
        assert len(idx) > n_lines + 64 * len(pts)  # more than the first buffer holds
