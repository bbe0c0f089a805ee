"""BVH ray casting against a brute-force loop, and the scene's rectangles."""

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.field import nsttf_like_field, track_field
from pihim.render.bvh import build_bvh, cast_rays
from pihim.render.scene import FACET, STRUCTURE, TOWER, box_rectangles, field_scene, fit_ground_plane


def _brute_force(o, u, v, ro, rd):
    n = np.cross(u, v)
    t_best = np.full(len(ro), np.inf)
    p_best = np.full(len(ro), -1)
    uu = np.einsum("ij,ij->i", u, u)
    vv = np.einsum("ij,ij->i", v, v)
    for i in range(len(ro)):
        with np.errstate(all="ignore"):
            t = np.einsum("ij,ij->i", o - ro[i], n) / (n @ rd[i])
        q = ro[i] + t[:, None] * rd[i] - o
        a = np.einsum("ij,ij->i", q, u) / uu
        b = np.einsum("ij,ij->i", q, v) / vv
        ok = (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        if ok.any():
            k = int(np.argmin(np.where(ok, t, np.inf)))
            t_best[i], p_best[i] = t[k], k
    return t_best, p_best


def _random_rectangles(rng, n):
    o = rng.uniform(-50, 50, (n, 3))
    u = rng.normal(size=(n, 3))
    w = np.cross(u, rng.normal(size=(n, 3)))
    u *= rng.uniform(0.5, 3, (n, 1)) / np.linalg.norm(u, axis=1, keepdims=True)
    w *= rng.uniform(0.5, 3, (n, 1)) / np.linalg.norm(w, axis=1, keepdims=True)
    return o, u, w


def test_nearest_hit_matches_brute_force():
    rng = np.random.default_rng(7)
    o, u, v = _random_rectangles(rng, 3000)
    bvh = build_bvh(o, u, v)
    ro = rng.uniform(-60, 60, (600, 3))
    rd = rng.normal(size=(600, 3))
    rd /= np.linalg.norm(rd, axis=1, keepdims=True)
    t, p = cast_rays(bvh, ro, rd)
    tb, pb = _brute_force(o, u, v, ro, rd)
    assert (pb >= 0).sum() > 50  # the test has hits to compare
    np.testing.assert_array_equal(p, pb)
    hit = pb >= 0
    np.testing.assert_allclose(t[hit], tb[hit], rtol=1e-12)
    assert np.all(np.isinf(t[~hit]))


def test_t_max_limits_hits():
    o, u, v = np.array([[0.0, 0.0, 5.0]]), np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]])
    bvh = build_bvh(o - [0.5, 0.5, 0], u, v)
    t, p = cast_rays(bvh, np.zeros((1, 3)), np.array([[0, 0, 1.0]]))
    assert p[0] == 0 and t[0] == pytest.approx(5.0)
    t, p = cast_rays(bvh, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), t_max=4.0)
    assert p[0] == -1


def test_bad_rectangles_refused():
    with pytest.raises(PihimInputError, match="perpendicular"):
        build_bvh([[0, 0, 0]], [[1, 0, 0]], [[1, 1, 0]])
    with pytest.raises(PihimInputError, match="non-zero"):
        build_bvh([[0, 0, 0]], [[0, 0, 0]], [[0, 1, 0]])
    with pytest.raises(PihimInputError, match="finite"):
        build_bvh([[0, np.nan, 0]], [[1, 0, 0]], [[0, 1, 0]])


def test_box_faces_point_outward():
    p0 = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    p1 = np.array([[2.0, 0.0, 0.0], [1.0, 2.0, 7.0]])
    o, u, v = box_rectangles(p0, p1, [0.2, 0.5], [0.0, 0.0, 1.0])
    centres = 0.5 * (p0 + p1)
    n = np.cross(u, v)
    face_centre = o + 0.5 * (u + v)
    out = np.einsum("ij,ij->i", n, face_centre - np.repeat(centres, 6, axis=0))
    assert np.all(out > 0)
    # the faces enclose the box: total area = 2 w^2 + 4 w L
    area = np.linalg.norm(n, axis=1).reshape(2, 6).sum(axis=1)
    np.testing.assert_allclose(area, [2 * 0.04 + 4 * 0.2 * 2, 2 * 0.25 + 4 * 0.5 * 4])


def test_field_scene_contents():
    field = nsttf_like_field()
    pose = track_field(field, np.array([0.3, -0.4, 0.866]))
    scene = field_scene(pose)
    n_h, n_f = len(field), field.spec.n_facets
    assert (scene.kind == FACET).sum() == n_h * n_f
    assert (scene.kind == TOWER).sum() == 5
    # torque tube and crossbars (mirror width) and ribs (mirror height) cut into facet-length pieces,
    # the pedestal whole: 6 + 5 * 5 + 5 * 6 + 1 boxes for NSTTF
    spec = field.spec
    along_w = round(spec.mirror_width_m / spec.facet_width_m)
    along_h = round(spec.mirror_height_m / spec.facet_width_m)
    pieces = along_w + spec.cols * along_h + spec.rows * along_w + 1
    members = 1 + spec.cols + spec.rows + 1
    assert pieces == 62
    # four sides per piece and two end caps per member (the caps between pieces are inside)
    faces = 4 * pieces + 2 * members
    assert (scene.kind == STRUCTURE).sum() == n_h * faces
    assert np.all(np.bincount(scene.heliostat[scene.kind == STRUCTURE]) == faces)
    # facet fronts face along the facet normals
    facets = scene.kind == FACET
    np.testing.assert_allclose(scene.bvh.normal[facets], pose.facet_normals.reshape(-1, 3), atol=1e-12)
    assert set(scene.facet[facets]) == set(range(1, n_f + 1))
    # the ground plane passes through the ground under the pivots
    z = scene.ground_height(field.pivots[:, 0], field.pivots[:, 1])
    np.testing.assert_allclose(z, field.ground_z, atol=1e-9)


def test_fit_ground_plane_recovers_a_plane():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-100, 100, (50, 2))
    z = 1.5 + 0.02 * xy[:, 0] - 0.01 * xy[:, 1]
    a, b, c = fit_ground_plane(np.column_stack([xy, z]))
    assert (a, b, c) == pytest.approx((1.5, 0.02, -0.01))
