"""Scan lines in the normals' planes and views from them, against brute-force oracles and hand cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pihim.field.kinematics import track_field
from pihim.field.layout import UFACET_AIM_POINT, Field, nsttf_like_field, nsttf_spec
from pihim.planning.lines import (
    VIEW_CAMERA_BLOCKED,
    VIEW_MISS,
    VIEW_OK,
    VIEW_REFLECTION_BLOCKED,
    ViewLimits,
    alignment_summary,
    candidate_targets,
    chain_lines,
    horizontal_normals,
    line_offsets,
    link_chains,
    pass_alignment,
    plane_links,
    views_from_lines,
)
from pihim.planning.model import ScanPass, Waypoint
from pihim.planning.sightlines import MirrorIndex

SUN = np.array([math.sin(math.radians(16.4)) * math.sin(math.radians(178.0)),
                math.sin(math.radians(16.4)) * math.cos(math.radians(178.0)), math.cos(math.radians(16.4))])
FIELD = nsttf_like_field()
POSE = track_field(FIELD, SUN, np.array(UFACET_AIM_POINT))
LIMITS = ViewLimits(max_range_m=60.0, min_reflection_elevation_deg=5.0, gimbal_pitch_min_deg=-90.0,
                    gimbal_pitch_max_deg=30.0, tower_box=None, keepout_box=None)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_candidates_are_in_front_and_turn_their_back() -> None:
    cand = candidate_targets(POSE, max_distance_m=50.0, max_off_axis_deg=20.0, max_lateral_m=6.1)
    assert len(cand) > 300
    c, n = POSE.mirror_centres, POSE.normals
    u = unit(c[cand.target] - c[cand.hua])
    assert np.all(np.einsum("ij,ij->i", u, n[cand.hua]) > 0)
    assert np.all(np.einsum("ij,ij->i", u, n[cand.target]) > 0)
    assert np.all(np.abs(cand.lateral_m) <= 6.1) and np.all(cand.forward_m > 0)
    assert np.all(np.degrees(np.arctan2(np.abs(cand.lateral_m), cand.forward_m)) <= 20.0 + 1e-9)
    # sorted by HUA, then distance
    assert np.all(np.diff(cand.hua) >= 0)
    same = np.diff(cand.hua) == 0
    assert np.all(np.diff(cand.distance_m)[same] >= 0)


def test_links_follow_the_normals_plane_not_the_nearest_heliostat() -> None:
    # HUA at the origin facing North (toward +y); next row 10 m North: one heliostat 0.5 m aside and a nearer
    # one 3 m aside; a third row 20 m North straight ahead
    names = ["8E1", "7E1", "7E2", "6E1"]
    pivots = np.array([[0.0, 0.0, 4.0], [0.5, 10.4, 4.0], [3.0, 9.6, 4.0], [0.0, 20.0, 4.0]])
    field = Field(tuple(names), pivots, nsttf_spec(), None)
    pose = track_field(field, np.array([0.0, 0.3, 0.954]), np.array([0.0, 300.0, 60.0]))
    cand = candidate_targets(pose, max_distance_m=50.0, max_off_axis_deg=25.0, max_lateral_m=6.1)
    link = plane_links(cand, 4, abreast_m=9.1)
    assert link[0] == 1  # the one nearest the normals' plane among the next row, although B is nearer
    assert link[1] == 3 and link[3] == -1
    chain = link_chains(link, pose.mirror_centres)
    assert chain[0] == chain[1] == chain[3]
    b, _ = horizontal_normals(pose)
    lines = chain_lines(chain, b, pose.mirror_centres[:, :2])
    k = chain[0]
    expect = unit(b[[0, 1, 3]].sum(axis=0))
    assert np.allclose(lines.direction[k], expect)
    assert np.allclose(lines.origin[k], pose.mirror_centres[[0, 1, 3], :2].mean(axis=0))


def test_line_offsets_start_at_zero_and_alternate() -> None:
    assert line_offsets(3.0, 1.0).tolist() == [0.0, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0]
    assert line_offsets(0.0, 1.0).tolist() == [0.0]


def test_views_agree_with_a_brute_force_ray_oracle(first_mirror) -> None:
    rng = np.random.default_rng(11)
    cand = candidate_targets(POSE, max_distance_m=50.0, max_off_axis_deg=20.0, max_lateral_m=6.1)
    pick = rng.choice(len(cand), size=160, replace=False)
    h, t = cand.hua[pick], cand.target[pick]
    b, _ = horizontal_normals(POSE)
    # lines along each HUA's own normals' plane, shifted sideways by -4..4 m, at 15-25 m
    across = np.stack([b[h, 1], -b[h, 0]], axis=1)
    origin = POSE.mirror_centres[h, :2] + rng.uniform(-4.0, 4.0, len(h))[:, None] * across
    alt = rng.uniform(15.0, 25.0, len(h))
    v = views_from_lines(POSE, MirrorIndex(POSE), LIMITS, h, t, origin, b[h], alt)
    assert np.allclose(v.camera[:, 2], alt)
    on_line = np.abs(np.einsum("ij,ij->i", v.camera[:, :2] - origin, across))
    assert np.all(on_line < 1e-9)
    n_ok = 0
    for i in range(len(h)):
        if v.code[i] < VIEW_MISS:
            continue
        cam, centre, normal = v.camera[i], POSE.mirror_centres[h[i]], POSE.normals[h[i]]
        d = unit(centre - cam)
        r = d - 2.0 * (d @ normal) * normal
        seen, _ = first_mirror(POSE, centre, r, int(h[i]))
        view_clear = first_mirror(POSE, cam, d, -1)[0] == h[i]  # the first mirror from the camera is the HUA
        if v.code[i] == VIEW_OK:
            assert seen == t[i] and view_clear
            n_ok += 1
        elif v.code[i] == VIEW_MISS:
            assert seen != t[i]
        elif v.code[i] == VIEW_REFLECTION_BLOCKED:
            assert seen == v.blocker[i] != t[i]
        elif v.code[i] == VIEW_CAMERA_BLOCKED:
            assert seen == t[i] and not view_clear
    assert n_ok >= 10 and np.sum(v.code == VIEW_MISS) >= 10


def test_camera_off_the_plane_is_refused_beyond_the_limit() -> None:
    cand = candidate_targets(POSE, max_distance_m=50.0, max_off_axis_deg=20.0, max_lateral_m=6.1)
    h, t = cand.hua[:40], cand.target[:40]
    b, _ = horizontal_normals(POSE)
    across = np.stack([b[h, 1], -b[h, 0]], axis=1)
    origin = POSE.mirror_centres[h, :2] + 5.0 * across
    free = views_from_lines(POSE, MirrorIndex(POSE), LIMITS, h, t, origin, b[h], np.full(40, 20.0), trace=False)
    tight = ViewLimits(**{**LIMITS.__dict__, "max_plane_offset_m": 3.0})
    cut = views_from_lines(POSE, MirrorIndex(POSE), tight, h, t, origin, b[h], np.full(40, 20.0), trace=False)
    assert np.allclose(free.plane_offset_m, 5.0, atol=1e-9)  # a line 5 m aside of the HUA's own plane
    assert not np.any(cut.ok) and np.any(free.code >= VIEW_MISS)


def test_pass_alignment_of_a_hand_made_pass() -> None:
    k = FIELD.index("8E3")
    b, _ = horizontal_normals(POSE)
    tilt = math.radians(4.0)  # fly 4 deg off the HUA's normals' plane, 1.5 m aside of it
    e = np.array([b[k, 0] * math.cos(tilt) - b[k, 1] * math.sin(tilt), b[k, 0] * math.sin(tilt) + b[k, 1] * math.cos(tilt)])
    across = np.array([b[k, 1], -b[k, 0]])
    cap = POSE.mirror_centres[k, :2] - 12.0 * b[k] + 1.5 * across

    def wp(xy: np.ndarray, capture: bool) -> Waypoint:
        return Waypoint(float(xy[0]), float(xy[1]), 20.0, 0.0, 0.0, 0.0, 0.0, -80.0, 5.0, kind="scan",
                        capture=capture, hua="8E3" if capture else None)

    p = ScanPass(index=0, azimuth_deg=0.0, altitude_m=20.0, gimbal_pitch_deg=-80.0, pairs=(("8E3", "7E3"),),
                 waypoints=(wp(cap - 18.0 * e, False), wp(cap, True), wp(cap + 9.0 * e, False)))
    (a,) = pass_alignment([p], FIELD, POSE)
    assert a.max_deviation_deg == pytest.approx(4.0, abs=1e-9)
    assert a.max_camera_offset_m == pytest.approx(1.5, abs=1e-9)
    assert a.max_off_line_m == pytest.approx(0.0, abs=1e-9)
    s = alignment_summary([p], FIELD, POSE)
    assert s["median_deviation_deg"] == pytest.approx(4.0) and s["max_camera_offset_m"] == pytest.approx(1.5)


def test_plane_azimuth_a_hair_west_of_north_is_0_not_360(monkeypatch) -> None:
    """``x % 360`` of a tiny negative azimuth is 360.0, outside the documented [0, 360): folded to 0."""
    from pihim.planning import lines

    p = ScanPass(index=0, azimuth_deg=0.0, altitude_m=20.0, gimbal_pitch_deg=-80.0, pairs=(("8E3", "7E3"),),
                 waypoints=(Waypoint(0.0, 0.0, 20.0, 0.0, 0.0, 0.0, 0.0, -80.0, 5.0, kind="scan", capture=True,
                                     hua="8E3"),))
    one = np.zeros(1)
    for x, want in ((-1e-300, 0.0), (-1.0, 360.0 - math.degrees(math.atan2(1.0, 1.0)))):
        monkeypatch.setattr(lines, "_capture_alignment", lambda *_a, x=x: (one, one, np.array([x, 1.0]), 0.0))
        (a,) = pass_alignment([p], FIELD, POSE)
        assert 0.0 <= a.plane_azimuth_deg < 360.0 and a.plane_azimuth_deg == pytest.approx(want)


def test_chains_straying_from_their_line_are_halved() -> None:
    from pihim.planning.lines import chain_lines, link_chains

    # one chain of 40 links along an arc of radius 300 m (every heliostat links to the next one inward)
    ang = np.radians(np.linspace(0.0, 120.0, 40))
    xy = np.stack([300.0 * np.sin(ang), 300.0 * np.cos(ang)], axis=1)
    centres = np.c_[xy, np.zeros(40)]
    link = np.r_[-1, np.arange(39)]  # k -> k - 1
    tangent = np.stack([np.cos(ang), -np.sin(ang)], axis=1)  # the "normals" follow the arc
    whole = link_chains(link, centres)
    assert len(np.unique(whole)) == 1
    for limit in (40.0, 10.0, 3.0):
        chain = link_chains(link, centres, limit, tangent)
        lines = chain_lines(chain, tangent, xy)
        assert np.abs(lines.lateral(chain, xy)).max() <= limit + 1e-9  # every piece within the limit of its line
        for c in np.unique(chain):  # pieces are runs of consecutive heliostats
            k = np.flatnonzero(chain == c)
            assert np.all(np.diff(k) == 1)
    assert len(np.unique(link_chains(link, centres, 3.0, tangent))) > len(np.unique(link_chains(link, centres, 40.0,
                                                                                               tangent))) > 1
    # a straight chain is never cut
    straight = np.c_[np.zeros(40), np.arange(40) * 12.0, np.zeros(40)]
    assert len(np.unique(link_chains(link, straight, 1.0, np.tile([0.0, 1.0], (40, 1))))) == 1
