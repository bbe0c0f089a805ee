"""3-D Stokes frames and s/p reflection, checked against explicit vector optics."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim.polarimetry.frames import (
    change_reference,
    field_direction,
    mueller_rotator,
    normalize,
    perpendicular_reference,
    rotation_angle_deg,
)
from pihim.polarimetry.reflection import reflect_direction, reflect_stokes
from pihim.polarimetry.stokes import aop_difference_deg, stokes_from_dolp_aop

unit3 = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.2).map(normalize)


def _beam(d, aop_deg, p=1.0):
    """A linearly polarized beam along d with AoP relative to the meridian reference."""
    e = perpendicular_reference(d)
    s = np.array([*stokes_from_dolp_aop(1.0, p, aop_deg), 0.0], dtype=float)
    return s, e


def test_rotation_angle_sign_looking_into_the_beam():
    x, y, z = np.eye(3)
    # beam along +z comes toward a viewer looking along -z: x right, y up -> x to y is counter-clockwise
    assert rotation_angle_deg(z, x, y) == pytest.approx(90.0)
    assert rotation_angle_deg(-z, x, y) == pytest.approx(-90.0)


def test_perpendicular_reference_is_meridian_up():
    d = normalize([0.3, -0.5, -0.8])  # light coming down
    e = perpendicular_reference(d)
    assert abs(np.dot(e, d)) < 1e-12 and e[2] > 0
    assert np.dot(np.cross(d, [0, 0, 1]), e) == pytest.approx(0.0, abs=1e-12)  # e lies in the vertical plane of d
    ez = perpendicular_reference([0.0, 0.0, -1.0])  # straight down: falls back to East
    assert np.allclose(ez, [1, 0, 0])


@settings(max_examples=60)
@given(d=unit3, aop=st.floats(0, 179.9), t=st.floats(-180, 180))
def test_change_reference_keeps_the_physical_field(d, aop, t):
    s, e = _beam(d, aop)
    # turn the reference axis by t about d (Rodrigues), re-express, compare field vectors
    k = d
    tr = np.radians(t)
    e2 = e * np.cos(tr) + np.cross(k, e) * np.sin(tr) + k * np.dot(k, e) * (1 - np.cos(tr))
    s2 = change_reference(s, d, e, e2)
    assert rotation_angle_deg(d, e, e2) == pytest.approx(t, abs=1e-6)
    f1, f2 = field_direction(s, d, e), field_direction(s2, d, e2)
    assert abs(np.dot(f1, f2)) == pytest.approx(1.0, abs=1e-9)
    assert s2[0] == pytest.approx(1.0) and np.hypot(s2[1], s2[2]) == pytest.approx(1.0)


def test_rotator_matches_2d_rotation_of_aop():
    s = np.array([1.0, *stokes_from_dolp_aop(1.0, 0.5, 70.0)[1:], 0.0])
    r = mueller_rotator(25.0) @ s
    assert aop_difference_deg(0.5 * np.degrees(np.arctan2(r[2], r[1])), 45.0) < 1e-9


PERFECT_CONDUCTOR = lambda cos_i: np.broadcast_to(np.diag([1.0, 1.0, -1.0, -1.0]), (*np.shape(cos_i), 4, 4))


@settings(max_examples=60)
@given(d=unit3, n=unit3, aop=st.floats(0, 179.9))
def test_perfect_mirror_matches_vector_optics(d, n, aop):
    """E_out = -E_in + 2 (E_in . n) n for a perfect conductor: the Stokes route must agree."""
    if abs(np.dot(d, n)) < 0.05:  # grazing: the plane of incidence is ill-defined
        return
    s, e = _beam(d, aop)
    e_field = field_direction(s, d, e)
    e_out = -e_field + 2.0 * np.dot(e_field, n) * n
    s_out, d_out, e_ref = reflect_stokes(s, d, e, n, PERFECT_CONDUCTOR)
    assert np.allclose(d_out, reflect_direction(d, n))
    assert abs(np.dot(e_ref, d_out)) < 1e-9 and abs(np.dot(e_out, d_out)) < 1e-9
    f = field_direction(s_out, d_out, e_ref)
    assert abs(np.dot(normalize(e_out), f)) == pytest.approx(1.0, abs=1e-7)
