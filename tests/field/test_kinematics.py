"""Heliostat kinematics: tracking, drive angles, frames, canting and geometry, with explicit signs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pihim.errors import PihimInputError
from pihim.field.kinematics import (
    FieldPose,
    apply_canting_deviation,
    back_structure,
    canting_angles,
    canting_deviation,
    design_facet_normals,
    drive_angles,
    facet_centres,
    facet_corners,
    facet_rotations,
    focal_lengths,
    heliostat_rotation,
    mirror_outline,
    normals_from_drive,
    reflect,
    rotation_from_drive,
    to_enu,
    track_field,
    tracking_normals,
)
from pihim.field.layout import (
    NSTTF_BCS_STANDBY,
    UFACET_AIM_POINT,
    nsttf_facet_centroids,
    nsttf_like_field,
)

E, N, U = np.eye(3)
SUN = np.array([math.sin(math.radians(30)) * math.sin(math.radians(235)),
                math.sin(math.radians(30)) * math.cos(math.radians(235)), math.cos(math.radians(30))])
FIELD = nsttf_like_field()
AIM = FIELD.default_aim_point
D = FIELD.spec.pivot_offset_m


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- tracking


def test_tracking_obeys_the_law_of_reflection() -> None:
    n, c = tracking_normals(FIELD.pivots, SUN, AIM, D)
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-14)
    assert np.allclose(c, FIELD.pivots + D * n, atol=1e-14)  # mirror centre in front of the pivot
    # sunlight travels along -s; reflected off n it must head from the mirror centre to the aim point
    assert np.allclose(reflect(-SUN, n), unit(AIM - c), atol=1e-12)
    assert np.allclose(n, unit(SUN + unit(AIM - c)), atol=1e-12)  # the bisector, at the fixed point
    # heliostats north of the tower face roughly south and up
    az, el = drive_angles(n)
    assert np.all((az > 90) & (az < 270)) and np.all((el > 0) & (el < 90))


def test_pivot_offset_matters_and_zero_offset_is_the_plain_bisector() -> None:
    n0, c0 = tracking_normals(FIELD.pivots, SUN, AIM, 0.0)
    assert np.allclose(c0, FIELD.pivots) and np.allclose(n0, unit(SUN + unit(AIM - FIELD.pivots)), atol=1e-15)
    n, _ = tracking_normals(FIELD.pivots, SUN, AIM, D)
    change = np.degrees(np.arccos(np.clip(np.sum(n * n0, -1), -1, 1)))
    assert 1e-3 < change.max() < 0.2  # a visible fraction of a milliradian, not noise


def test_tracking_independent_solver() -> None:
    """Solve n = bisector(s, a - p - d n) with scipy for one heliostat and compare."""
    from scipy.optimize import fsolve

    p = FIELD.pivot("5W1")

    def residual(angles: np.ndarray) -> np.ndarray:
        m = normals_from_drive(*angles)
        target = unit(SUN + unit(AIM - (p + D * m)))
        az, el = drive_angles(target)
        return np.array([(float(az) - angles[0] + 180) % 360 - 180, float(el) - angles[1]])

    sol = fsolve(residual, np.array([180.0, 45.0]), xtol=1e-13)
    n, _ = tracking_normals(p, SUN, AIM, D)
    assert np.allclose(n, normals_from_drive(*sol), atol=1e-10)


def test_tracking_broadcasts() -> None:
    aims = np.tile(np.array(UFACET_AIM_POINT), (len(FIELD), 1))
    aims[0] = NSTTF_BCS_STANDBY
    n, _ = tracking_normals(FIELD.pivots, SUN, aims, D)
    assert np.allclose(n[1:], tracking_normals(FIELD.pivots[1:], SUN, UFACET_AIM_POINT, D)[0], atol=1e-14)
    assert np.allclose(n[0], tracking_normals(FIELD.pivots[0], SUN, NSTTF_BCS_STANDBY, D)[0], atol=1e-14)
    suns = normals_from_drive([90.0, 180.0, 270.0], [20.0, 60.0, 20.0])[:, None, :]  # (T, 1, 3)
    nt, ct = tracking_normals(FIELD.pivots, suns, AIM, D)
    assert nt.shape == ct.shape == (3, len(FIELD), 3)
    assert np.allclose(nt[1], tracking_normals(FIELD.pivots, suns[1, 0] * 7.0, AIM, D)[0], atol=1e-14)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sun_dir": [0.0, 0.0, 0.0]}, "zero vector"),
        ({"sun_dir": [0.0, 1.0]}, "3 components"),
        ({"pivots": [[0.0, np.nan, 0.0]]}, "finite"),
        ({"aim_point": [0.0, 0.0, 0.0], "pivots": [[0.0, 0.0, 0.0]], "pivot_offset_m": 0.0}, "undefined"),
        ({"sun_dir": [0.0, 1.0, 0.0], "pivots": [[0.0, 0.0, 0.0]], "aim_point": [0.0, -10.0, 0.0],
          "pivot_offset_m": 0.0}, "undefined"),
    ],
)
def test_tracking_errors(kwargs: dict, message: str) -> None:
    args = {"pivots": FIELD.pivots[:3], "sun_dir": SUN, "aim_point": AIM, "pivot_offset_m": D} | kwargs
    with pytest.raises(PihimInputError, match=message):
        tracking_normals(**args)


# ----------------------------------------------------------------------------- drive angles


@pytest.mark.parametrize(
    ("normal", "az", "el"),
    [(-N, 180.0, 0.0), (N, 0.0, 0.0), (E, 90.0, 0.0), (-E, 270.0, 0.0), (unit(E + U), 90.0, 45.0),
     (unit(-N + math.sqrt(3) * U), 180.0, 60.0), (U, 180.0, 90.0)],
)
def test_drive_angles_explicit(normal: np.ndarray, az: float, el: float) -> None:
    a = drive_angles(normal)
    assert math.isclose(float(a.azimuth_deg), az, abs_tol=1e-12) and math.isclose(float(a.elevation_deg), el,
                                                                                    abs_tol=1e-12)
    assert math.isclose(float(a.back_azimuth_deg), (az + 180) % 360) and math.isclose(float(a.back_elevation_deg), -el)
    if el < 90:
        assert np.allclose(normals_from_drive(az, el), normal, atol=1e-15)
        back = normals_from_drive(a.back_azimuth_deg, a.back_elevation_deg)
        assert np.allclose(back, -normal, atol=1e-15)


@given(st.floats(0.0, 359.999), st.floats(-89.9, 89.9))
def test_drive_angles_round_trip(az: float, el: float) -> None:
    a = drive_angles(normals_from_drive(az, el))
    assert abs((float(a.azimuth_deg) - az + 180) % 360 - 180) < 1e-9 and abs(float(a.elevation_deg) - el) < 1e-9


# ----------------------------------------------------------------------------- heliostat frame


@pytest.mark.parametrize(
    ("normal", "x", "y"),
    [
        (-N, E, U),  # facing South, seen from the South: right is East
        (N, -E, U),  # facing North, seen from the North: right is West
        (E, N, U),  # facing East: right is North
        (-E, -N, U),
        (U, E, N),  # face up: the limit of a South-facing mirror tilting up
        (unit(-N + U), E, unit(N + U)),  # tilted South-facing mirror: top edge leans North
    ],
)
def test_heliostat_frame_explicit(normal: np.ndarray, x: np.ndarray, y: np.ndarray) -> None:
    r = heliostat_rotation(normal)
    assert np.allclose(r[:, 0], x, atol=1e-15) and np.allclose(r[:, 1], y, atol=1e-15)
    assert np.allclose(r[:, 2], normal, atol=1e-15)


def test_heliostat_frame_is_right_as_seen_by_a_viewer() -> None:
    """An observer in front of the mirror, looking at it with its y axis up, has x on the right."""
    rng = np.random.default_rng(1)
    n = unit(rng.normal(size=(200, 3)) + [0, 0, 0.5])
    r = heliostat_rotation(n)
    forward, up = -n, r[..., 1]  # looking at the face, head along the heliostat y axis
    right = np.cross(forward, up)  # right-handed camera: right = forward x up
    assert np.allclose(right, r[..., 0], atol=1e-12)
    assert np.allclose(np.linalg.det(r), 1.0) and np.allclose(np.swapaxes(r, -1, -2) @ r, np.eye(3), atol=1e-12)
    assert np.allclose(r[..., 2, 0], 0.0)  # x horizontal (az-el drive)
    assert np.all(r[..., 2, 1] >= 0)  # the top edge is never below the bottom edge (az-el drive)
    az, el = drive_angles(n)
    ok = el < 89.0
    assert np.allclose(rotation_from_drive(az, el)[ok], r[ok], atol=1e-12)
    assert np.allclose(rotation_from_drive(123.0, 90.0)[:, 0], [-math.cos(math.radians(123)),
                                                               math.sin(math.radians(123)), 0.0])


def test_to_enu() -> None:
    n, c = tracking_normals(FIELD.pivots[:4], SUN, AIM, D)
    r = heliostat_rotation(n)
    q = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    out = to_enu(r, c, q)
    assert out.shape == (4, 2, 3) and np.allclose(out[:, 1], c)
    assert np.allclose(out[2, 0], c[2] + r[2] @ q[0])
    per = to_enu(r, c, np.broadcast_to(q, (4, 2, 3)), per_heliostat=True)
    assert np.allclose(per, out)


# ----------------------------------------------------------------------------- canting


def test_design_canting_closed_form_is_the_paraboloid_normal() -> None:
    f = 75.0
    c = nsttf_facet_centroids()
    n = design_facet_normals(c, f)
    h = 1e-5  # finite-difference gradient of z = (x^2 + y^2) / (4 f), an independent route

    def z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (x**2 + y**2) / (4 * f)

    gx = (z(c[:, 0] + h, c[:, 1]) - z(c[:, 0] - h, c[:, 1])) / (2 * h)
    gy = (z(c[:, 0], c[:, 1] + h) - z(c[:, 0], c[:, 1] - h)) / (2 * h)
    assert np.allclose(n, unit(np.stack([-gx, -gy, np.ones(25)], -1)), atol=1e-10)
    # the normal line meets the axis at 2 f + z_p (centre of curvature), not at the focus
    p = np.stack([c[:, 0], c[:, 1], z(c[:, 0], c[:, 1])], -1)
    off = np.abs(c[:, 0]) > 0
    s = -p[off, 0] / n[off, 0]
    hit = p[off] + s[:, None] * n[off]
    assert np.allclose(hit[:, :2], 0.0, atol=1e-12) and np.allclose(hit[:, 2], 2 * f + p[off, 2], atol=1e-9)


@pytest.mark.parametrize("f", [5.0, 55.0, 100.0, 186.8])
def test_on_axis_rays_reflect_through_the_focus(f: float) -> None:
    c = nsttf_facet_centroids()
    n = design_facet_normals(c, f)
    down = np.array([0.0, 0.0, -1.0])  # arriving along the axis
    r = reflect(down, n)
    focus = np.array([0.0, 0.0, f])

    def miss(points: np.ndarray) -> np.ndarray:
        v = focus - points
        return np.linalg.norm(v - np.sum(v * r, -1)[:, None] * r, axis=-1)

    on_paraboloid = c.copy()
    on_paraboloid[:, 2] = (c[:, 0] ** 2 + c[:, 1] ** 2) / (4 * f)
    assert np.max(miss(on_paraboloid)) < 1e-12 * f  # exact for centres on the paraboloid
    # actual (flat) facet centres: the ray crosses the axis (z_p - z_c) lower; lateral miss is tiny
    assert np.max(miss(c)) <= np.max(np.abs(on_paraboloid[:, 2] - c[:, 2]) * np.linalg.norm(r[:, :2], axis=-1)) + 1e-12


def test_canting_magnitudes_at_100_m() -> None:
    """At f = 100 m the NSTTF corner facets tilt by about 13-14 mrad per axis (19 mrad in all)."""
    n = design_facet_normals(nsttf_facet_centroids(), 100.0)
    az, el = canting_angles(n)
    assert math.isclose(az[0], 1e3 * math.atan(2.7941016 / 200.0), rel_tol=1e-12)  # facet 1: toward +x
    assert math.isclose(el[0], -1e3 * math.asin(2.5655016 / 200.0 / math.hypot(1.0, 3.7930 / 200.0)), rel_tol=1e-4)
    assert 13.5 < az[0] < 14.5 and -13.5 < el[0] < -12.5 and az[12] == 0 and el[12] == 0
    # every facet tilts toward the centre: signs opposite to its position
    c = nsttf_facet_centroids()
    assert np.all(np.sign(az) == -np.sign(c[:, 0])) and np.all(np.sign(el) == -np.sign(c[:, 1]))
    total = np.degrees(np.arccos(n[:, 2])) * math.pi / 180 * 1e3
    assert 18.5 < total.max() < 19.5
    assert np.allclose(design_facet_normals(nsttf_facet_centroids(), np.inf), [0, 0, 1])
    with pytest.raises(PihimInputError):
        design_facet_normals(nsttf_facet_centroids(), 0.0)


def test_focal_lengths_are_slant_ranges() -> None:
    f = focal_lengths(FIELD.pivots, AIM)
    assert np.allclose(f, np.linalg.norm(AIM - FIELD.pivots, axis=-1))
    assert design_facet_normals(nsttf_facet_centroids(), f).shape == (len(FIELD), 25, 3)


@pytest.mark.parametrize(
    ("az", "el", "expected"),
    [(5.0, 0.0, (math.sin(5e-3), 0.0, math.cos(5e-3))),  # azimuth tilts the normal toward +x
     (-5.0, 0.0, (-math.sin(5e-3), 0.0, math.cos(5e-3))),
     (0.0, 5.0, (0.0, math.sin(5e-3), math.cos(5e-3))),  # elevation tilts the normal toward +y
     (0.0, -5.0, (0.0, -math.sin(5e-3), math.cos(5e-3)))],
)
def test_canting_deviation_signs(az: float, el: float, expected: tuple[float, float, float]) -> None:
    n = apply_canting_deviation([0.0, 0.0, 1.0], az, el)
    assert np.allclose(n, expected, atol=1e-15)
    back = canting_deviation([0.0, 0.0, 1.0], n)
    assert math.isclose(float(back[0]), az, abs_tol=1e-12) and math.isclose(float(back[1]), el, abs_tol=1e-12)


def test_canting_deviation_is_rotations_about_heliostat_axes() -> None:
    """Independent oracle: scipy rotations, elevation (about -x) first, then azimuth (about +y)."""
    design = design_facet_normals(nsttf_facet_centroids(), 40.0)
    rng = np.random.default_rng(7)
    az, el = rng.uniform(-10, 10, 25), rng.uniform(-10, 10, 25)
    rot = Rotation.from_rotvec(np.c_[np.zeros(25), az * 1e-3, np.zeros(25)]) * Rotation.from_rotvec(
        np.c_[-el * 1e-3, np.zeros(25), np.zeros(25)])
    assert np.allclose(apply_canting_deviation(design, az, el), rot.apply(design), atol=1e-15)
    # to first order the deviations are the changes of the normal's x and y components
    small = apply_canting_deviation(design, 0.1, -0.2) - design
    assert np.allclose(small[:, 0], 1e-4, rtol=0.05) and np.allclose(small[:, 1], -2e-4, rtol=0.05)


@settings(max_examples=200)
@given(st.floats(-60, 60), st.floats(-60, 60), st.floats(-30, 30), st.floats(-30, 30))
def test_canting_deviation_round_trip(cx: float, cy: float, az: float, el: float) -> None:
    design = unit(np.array([cx * 1e-3, cy * 1e-3, 1.0]))
    actual = apply_canting_deviation(design, az, el)
    a, e = canting_deviation(design, actual)
    assert abs(float(a) - az) < 1e-9 and abs(float(e) - el) < 1e-9


def test_canting_angles_and_facet_frames() -> None:
    n = design_facet_normals(nsttf_facet_centroids(), 60.0)
    az, el = canting_angles(n)
    a2, e2 = canting_deviation([0.0, 0.0, 1.0], n)
    assert np.allclose(az, a2, atol=1e-12) and np.allclose(el, e2, atol=1e-12)
    fr = facet_rotations(n)
    assert np.allclose(fr[..., 2], n) and np.allclose(np.linalg.det(fr), 1.0)
    assert np.allclose(fr[..., 1, 0], 0.0)  # facet x stays in the heliostat x-z plane (turned about y only)
    assert np.allclose(fr, Rotation.from_rotvec(np.c_[np.zeros(25), az * 1e-3, np.zeros(25)]).as_matrix()
                       @ Rotation.from_rotvec(np.c_[-el * 1e-3, np.zeros(25), np.zeros(25)]).as_matrix(), atol=1e-14)


# ----------------------------------------------------------------------------- geometry


@pytest.fixture(scope="module")
def pose() -> FieldPose:
    return track_field(FIELD, SUN)


def test_track_field(pose: FieldPose) -> None:
    n, c = tracking_normals(FIELD.pivots, SUN, AIM, D)
    assert np.allclose(pose.normals, n) and np.allclose(pose.mirror_centres, c)
    assert np.allclose(pose.focal_lengths_m, np.linalg.norm(AIM - FIELD.pivots, axis=-1))
    assert pose.facet_normals.shape == pose.facet_centres.shape == (len(FIELD), 25, 3)
    assert np.allclose(pose.facet_normals[:, 12], pose.normals)  # the centre facet is not canted
    # the centre facet centroid is the mirror centre: pivot + offset along the normal
    assert np.allclose(pose.facet_centres[:, 12] - FIELD.pivots, D * pose.normals, atol=1e-14)
    assert np.allclose(pose.facet_centres[:, 0] - pose.mirror_centres,
                       np.einsum("nij,j->ni", pose.rotations, nsttf_facet_centroids()[0]))
    assert np.allclose(facet_centres(pose.rotations, pose.mirror_centres, nsttf_facet_centroids()), pose.facet_centres)
    custom = track_field(FIELD, SUN, UFACET_AIM_POINT, canting_focal_length_m=100.0)
    assert np.allclose(custom.focal_lengths_m, 100.0)
    assert np.allclose(custom.normals, tracking_normals(FIELD.pivots, SUN, UFACET_AIM_POINT, D)[0])
    assert np.allclose(pose.drive.azimuth_deg, drive_angles(pose.normals).azimuth_deg)


def test_on_axis_canted_heliostat_focuses_on_the_aim_point() -> None:
    """Sun straight behind the aim (on-axis): every facet sends its centre ray to the aim point."""
    name = "8E3"
    p = FIELD.pivot(name)
    aim = np.array(AIM)
    axis = unit(aim - p)
    one = FIELD.subset([name])
    pose = track_field(one, axis)  # sun on the axis
    ray = reflect(-axis, pose.facet_normals[0])
    v = aim - pose.facet_centres[0]
    miss = np.linalg.norm(v - np.sum(v * ray, -1)[:, None] * ray, axis=-1)
    assert miss.max() < 0.01  # metres at ~80 m; un-canted (flat) facets would miss by up to 3.4 m
    flat = reflect(-axis, pose.normals[0])
    miss_flat = np.linalg.norm(v - np.sum(v * flat, -1)[:, None] * flat, axis=-1)
    assert miss_flat.max() > 2.0


def test_facet_corners(pose: FieldPose) -> None:
    corners = pose.facet_corners()
    assert corners.shape == (len(FIELD), 25, 4, 3)
    w = FIELD.spec.facet_width_m
    assert np.allclose(np.linalg.norm(corners[..., 1, :] - corners[..., 0, :], axis=-1), w)
    assert np.allclose(np.linalg.norm(corners[..., 1, :] - corners[..., 2, :], axis=-1), w)
    assert np.allclose(corners.mean(axis=2), pose.facet_centres)
    # each facet is a flat square perpendicular to its own (canted) normal
    edge = corners - pose.facet_centres[:, :, None, :]
    assert np.allclose(np.einsum("nfkj,nfj->nfk", edge, pose.facet_normals), 0.0, atol=1e-12)
    # corner order: top left, top right, bottom right, bottom left seen from the front
    x, y = pose.rotations[:, None, :, 0], pose.rotations[:, None, :, 1]
    sx = np.sign(np.einsum("nfkj,nfj->nfk", edge, np.broadcast_to(x, edge.shape[:2] + (3,))))
    sy = np.sign(np.einsum("nfkj,nfj->nfk", edge, np.broadcast_to(y, edge.shape[:2] + (3,))))
    assert np.all(sx == [-1, 1, 1, -1]) and np.all(sy == [1, 1, -1, -1])
    # flat facets tile the outline: facet 1's top-left corner is the outline's top-left corner (bar set-back)
    flat = pose.facet_corners(np.broadcast_to([0.0, 0.0, 1.0], (25, 3)))
    outline = pose.mirror_outline()
    setback = nsttf_facet_centroids()[0, 2] * pose.normals
    assert np.allclose(flat[:, 0, 0] - setback, outline[:, 0], atol=1e-12)
    assert np.allclose(flat[:, 24, 2] - setback, outline[:, 2], atol=1e-12)
    assert np.allclose(outline.mean(axis=1), pose.mirror_centres)  # includes the pivot offset
    assert np.allclose(np.linalg.norm(outline[:, 1] - outline[:, 0], axis=-1), FIELD.spec.mirror_width_m)
    # per-heliostat normals (deviations) are accepted
    dev = apply_canting_deviation(pose.facet_normals_local, 3.0, -2.0)
    assert facet_corners(pose.rotations, pose.mirror_centres, nsttf_facet_centroids(), dev, w, w).shape == corners.shape


def test_back_structure(pose: FieldPose) -> None:
    b = pose.back_structure()
    assert b.segments.shape == (len(FIELD), 12, 2, 3)
    assert b.kinds.count("rib") == 5 and b.kinds.count("crossbar") == 5
    tube = b.of_kind("torque_tube")[:, 0]
    assert np.allclose(tube.mean(axis=1), FIELD.pivots, atol=1e-12)  # through the pivot
    direction = unit(tube[:, 1] - tube[:, 0])
    assert np.allclose(direction, pose.rotations[..., 0]) and np.allclose(direction[:, 2], 0.0, atol=1e-15)
    ped = b.of_kind("pedestal")[:, 0]
    assert np.allclose(ped[:, 1], FIELD.pivots) and np.allclose(ped[:, 0], FIELD.pivots - [0, 0, 4.02])
    ribs = b.of_kind("rib")
    assert np.allclose(np.einsum("nsj,nj->ns", unit(ribs[:, :, 1] - ribs[:, :, 0]), pose.rotations[..., 1]), 1.0)
    body = b.segments[:, :-1]
    # members lie in the plane through the pivot, behind the mirror
    off = np.einsum("nskj,nj->nsk", body - FIELD.pivots[:, None, None, :], pose.normals)
    assert np.allclose(off, 0.0, atol=1e-12)
    assert np.allclose(back_structure(pose.rotations, pose.mirror_centres, FIELD.spec).segments, b.segments)
    assert np.allclose(mirror_outline(pose.rotations, pose.mirror_centres, FIELD.spec), pose.mirror_outline())


def test_with_drive_matches_tracking_at_the_tracked_angles_and_moves_otherwise():
    from pihim.field import nsttf_like_field, track_field

    field = nsttf_like_field()
    pose = track_field(field, np.array([0.3, -0.4, 0.866]))
    same = pose.with_drive(pose.drive.azimuth_deg, pose.drive.elevation_deg)
    np.testing.assert_allclose(same.normals, pose.normals, atol=1e-12)
    np.testing.assert_allclose(same.mirror_centres, pose.mirror_centres, atol=1e-12)
    np.testing.assert_allclose(same.facet_normals, pose.facet_normals, atol=1e-12)
    up = pose.with_drive(180.0, 90.0)  # every mirror face-up
    np.testing.assert_allclose(up.normals, np.tile([0.0, 0.0, 1.0], (len(field), 1)), atol=1e-12)
    np.testing.assert_allclose(up.mirror_centres[:, 2], field.pivots[:, 2] + field.spec.pivot_offset_m)
    np.testing.assert_allclose(up.facet_normals_local, pose.facet_normals_local)


def test_track_field_refuses_a_sun_below_the_horizon_and_shapes_it_cannot_use():
    """A sun below the horizon gave mirrors facing the ground; wrong shapes were numpy broadcasting errors."""
    field = nsttf_like_field()
    for sun, says in (([0.3, -0.4, -0.2], "not above the horizon"), ([0.3, -0.4, 0.0], "not above the horizon"),
                      ([[0.0, 0.0, 1.0]] * 2, r"one direction, shape \(3,\)"), ([0.0, 1.0], "3 components")):
        with pytest.raises(PihimInputError, match=says):
            track_field(field, sun)
    with pytest.raises(PihimInputError, match=r"canting_focal_length_m must be one focal length or one per"):
        track_field(field, [0.0, 0.0, 1.0], canting_focal_length_m=np.ones(5))
    with pytest.raises(PihimInputError, match="aim_point must be one point or one per heliostat"):
        track_field(field, [0.0, 0.0, 1.0], np.ones((5, 3)))
    with pytest.raises(PihimInputError, match="field must be a pihim.field.Field"):
        track_field(None, [0.0, 0.0, 1.0])
    flat = track_field(field, [0.0, 0.0, 1.0], canting_focal_length_m=np.inf)  # inf: flat facets
    np.testing.assert_allclose(flat.facet_normals_local[..., 2], 1.0)


def test_zero_and_non_unit_normals_are_refused():
    """A zero normal gave NaN drive angles and rotations; reflect() returned the direction unchanged for a zero
    normal and tripled it for [0, 0, 2]."""
    for fn in (drive_angles, heliostat_rotation):
        with pytest.raises(PihimInputError, match="normals must be non-zero vectors"):
            fn([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    for n in ([0.0, 0.0, 0.0], [0.0, 0.0, 2.0]):
        with pytest.raises(PihimInputError, match="normals must be unit vectors"):
            reflect([0.0, 0.0, -1.0], n)
    np.testing.assert_allclose(reflect([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]), [0.0, 0.0, 1.0])
