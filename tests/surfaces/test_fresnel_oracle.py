"""Independent checks of the Fresnel code: closed forms (Born & Wolf) and Mitsuba 3 as an oracle.

Conventions pinned here (see ``pihim.surfaces.fresnel``): s is the Mueller x
axis; ``N = n + ik`` with time dependence ``exp(-i omega t)``; ``r_s``, ``r_p``
as in Born & Wolf sec. 1.5.2 (the paper's eqs. 6-7), so ``r_p = -r_s`` at
normal incidence; circular entries ``M23 = -M32 = Im(r_s r_p*)`` (paper eq. 5).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim.errors import PihimInputError
from pihim.surfaces.fresnel import (
    brewster_angle_deg,
    fresnel_amplitudes,
    fresnel_reflectance,
    fresnel_reflection_mueller,
    fresnel_transmission_mueller,
)

SILVER = complex(0.06, 3.586)  # Johnson & Christy 1972, 548.6 nm
GOLD = complex(0.29, 2.87)  # Johnson & Christy 1972, near 564 nm (order of magnitude only)
ALUMINIUM = complex(0.96, 6.69)  # a strongly absorbing metal, for coverage


# ------------------------------------------------------------------ closed forms


@settings(max_examples=50, deadline=None)
@given(n=st.floats(1.05, 3.0))
def test_brewster_angle_kills_p_reflection(n):
    c = np.cos(np.radians(brewster_angle_deg(1.0, n)))
    r_s, r_p = fresnel_reflectance(c, 1.0, n)
    assert r_p < 1e-28
    assert r_s > 0.0
    m = fresnel_reflection_mueller(c, 1.0, n)
    assert m[0, 1] == pytest.approx(m[0, 0])  # fully s-polarized: M01 = M00 (s is the x axis)


def test_brewster_angle_of_glass():
    assert brewster_angle_deg(1.0, 1.5) == pytest.approx(np.degrees(np.arctan(1.5)))
    assert fresnel_reflectance(np.cos(np.arctan(1.5)), 1.0, 1.5)[1] == pytest.approx(0.0, abs=1e-30)


@pytest.mark.parametrize("n1, n2", [(1.0, 1.5), (1.0, 1.33), (1.5, 1.0), (1.0, 2.4)])
def test_normal_incidence_dielectric(n1, n2):
    r_s, r_p = fresnel_amplitudes(1.0, n1, n2)
    expected = ((n2 - n1) / (n2 + n1)) ** 2
    assert abs(r_s) ** 2 == pytest.approx(expected, rel=1e-12)
    assert abs(r_p) ** 2 == pytest.approx(expected, rel=1e-12)
    assert r_p == pytest.approx(-r_s)  # the paper's sign convention (eqs. 6-7)


@pytest.mark.parametrize("n", [SILVER, GOLD, ALUMINIUM, complex(1.5, 0.3)])
def test_normal_incidence_metal(n):
    expected = ((n.real - 1) ** 2 + n.imag**2) / ((n.real + 1) ** 2 + n.imag**2)
    r_s, r_p = fresnel_reflectance(1.0, 1.0, n)
    assert r_s == pytest.approx(expected, rel=1e-12)
    assert r_p == pytest.approx(expected, rel=1e-12)
    m = fresnel_reflection_mueller(1.0, 1.0, n)
    assert np.allclose(m, expected * np.diag([1.0, 1.0, -1.0, -1.0]), atol=1e-14)


def test_perfect_conductor_limit():
    """k -> infinity: r_s -> -1, r_p -> +1 at any angle (the basis of the ideal mirror)."""
    for c in (1.0, 0.7, 0.2):
        r_s, r_p = fresnel_amplitudes(c, 1.0, complex(0.0, 1e7))
        assert r_s == pytest.approx(-1.0, abs=1e-6) and r_p == pytest.approx(1.0, abs=1e-6)


def _tir_angles():
    crit = np.degrees(np.arcsin(1.0 / 1.5))
    return np.linspace(crit + 0.5, 89.5, 25)


def test_total_internal_reflection_phase_matches_born_wolf():
    """Glass (1.5) to air beyond the critical angle (Born & Wolf sec. 1.5.4).

    |r_s| = |r_p| = 1 and the relative phase ``delta = arg(r_s) - arg(r_p)``
    (B&W ``delta_perp - delta_par``) obeys B&W eq. (60)::

        tan(delta / 2) = cos_i sqrt(sin^2 i - n^2) / sin^2 i,   n = n2 / n1,

    with the individual phases ``tan(delta_s / 2) = -sqrt(sin^2 i - n^2) / cos_i``
    and ``tan(delta_p / 2) = -sqrt(sin^2 i - n^2) / (n^2 cos_i)``. In the
    Mueller matrix ``M22 = cos(delta)``, ``M23 = sin(delta)``,
    ``M32 = -sin(delta)``: light linearly polarized at +45 deg from s
    (S2 = +1) leaves with ``S3 = -sin(delta) < 0``.
    """
    i = np.radians(_tir_angles())
    c, s2 = np.cos(i), np.sin(i) ** 2
    n = 1.0 / 1.5
    r_s, r_p = fresnel_amplitudes(c, 1.5, 1.0)
    assert np.allclose(np.abs(r_s), 1.0, atol=1e-12) and np.allclose(np.abs(r_p), 1.0, atol=1e-12)
    root = np.sqrt(s2 - n**2)
    assert np.allclose(np.tan(np.angle(r_s) / 2), -root / c, rtol=1e-10)
    assert np.allclose(np.tan(np.angle(r_p) / 2), -root / (n**2 * c), rtol=1e-10)
    delta = np.angle(r_s * np.conj(r_p))
    assert np.all((delta > 0) & (delta < np.pi / 2))
    assert np.allclose(np.tan(delta / 2), c * root / s2, rtol=1e-10)
    m = fresnel_reflection_mueller(c, 1.5, 1.0)
    assert np.allclose(m[:, 0, 0], 1.0) and np.allclose(m[:, 0, 1], 0.0, atol=1e-12)
    assert np.allclose(m[:, 2, 2], np.cos(delta)) and np.allclose(m[:, 3, 3], np.cos(delta))
    assert np.allclose(m[:, 2, 3], np.sin(delta)) and np.allclose(m[:, 3, 2], -np.sin(delta))
    out = m @ np.array([1.0, 0.0, 1.0, 0.0])
    assert np.all(out[:, 3] < 0)  # S2 -> S3 conversion with a pinned sign


def test_s3_sign_means_counter_clockwise_looking_into_the_beam():
    """What ``S3 > 0`` means physically with these amplitudes (time dependence ``exp(-i omega t)``).

    After total internal reflection of light at +45 deg, the real field in the
    reflected (s, p) frame is ``E(t) = Re[(r_s, r_p) exp(-i omega t)]``. Its
    sense of rotation seen looking into the beam (d toward the viewer, s
    right, p = d x s up) is the sign of ``E_s dE_p/dt - E_p dE_s/dt``
    (counter-clockwise > 0). The Mueller matrix must give S3 of that sign.
    """
    for deg in _tir_angles():
        c = np.cos(np.radians(deg))
        r_s, r_p = fresnel_amplitudes(c, 1.5, 1.0)
        t = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
        e_s, e_p = np.real(r_s * np.exp(-1j * t)), np.real(r_p * np.exp(-1j * t))
        de_s, de_p = np.real(-1j * r_s * np.exp(-1j * t)), np.real(-1j * r_p * np.exp(-1j * t))
        sense = np.mean(e_s * de_p - e_p * de_s)
        s3 = (fresnel_reflection_mueller(c, 1.5, 1.0) @ np.array([1.0, 0.0, 1.0, 0.0]))[3]
        assert abs(sense) > 1e-3 and np.sign(s3) == np.sign(sense)


def test_fresnel_rhomb_quarter_wave():
    """Born & Wolf sec. 1.5.4: glass n = 1.51 gives delta = 45 deg at 48.6 and 54.6 deg (Fresnel rhomb)."""
    for deg in (48.62, 54.62):
        r_s, r_p = fresnel_amplitudes(np.cos(np.radians(deg)), 1.51, 1.0)
        assert np.degrees(np.angle(r_s * np.conj(r_p))) == pytest.approx(45.0, abs=0.01)


# ------------------------------------------------------------------ Mitsuba 3 oracle

#: S3 handedness flip between pihim and Mitsuba (see test_mitsuba_reflection_agrees).
FLIP_S3 = np.diag([1.0, 1.0, 1.0, -1.0])
COS = [1.0, 0.95, 0.8, 0.6, 0.4, 0.2, 0.05]
INDICES = [1.5, 1.33, 2.4, 1.0 / 1.5, SILVER, GOLD, ALUMINIUM, complex(1.5, 0.3)]


@pytest.fixture(scope="module")
def mi():
    mitsuba = pytest.importorskip("mitsuba")
    for variant in ("scalar_spectral_polarized", "scalar_rgb_polarized", "scalar_mono_polarized"):
        if variant in mitsuba.variants():
            mitsuba.set_variant(variant)
            return mitsuba
    pytest.skip("no scalar polarized Mitsuba variant installed")


def _eta(mi, n):
    """Mitsuba's relative index: eta = n - ik, i.e. conj(N)."""
    import drjit as dr

    n = complex(n)
    return dr.scalar.Complex2f(n.real, -n.imag)


@pytest.mark.parametrize("n", INDICES, ids=str)
@pytest.mark.parametrize("c", COS)
def test_mitsuba_amplitudes_are_the_complex_conjugates(mi, n, c):
    """``mi.fresnel_polarized(cos, conj(N))`` returns ``(conj(r_s), conj(r_p))``.

    Same s/p sign convention (including the p amplitude: r_p = -r_s at
    normal incidence), opposite time convention (``exp(+i omega t)``).
    """
    a_s, a_p = (complex(a.real, a.imag) for a in mi.fresnel_polarized(c, _eta(mi, n))[:2])
    r_s, r_p = fresnel_amplitudes(c, 1.0, n)
    assert a_s == pytest.approx(np.conj(r_s), abs=2e-6)
    assert a_p == pytest.approx(np.conj(r_p), abs=2e-6)


@pytest.mark.parametrize("n", INDICES, ids=str)
@pytest.mark.parametrize("c", COS)
def test_mitsuba_reflection_agrees(mi, n, c):
    """Full 4x4 comparison with ``mi.mueller.specular_reflection`` (float32: 2e-6).

    Both use s as the x axis and the layout ``[[A, B], [B, A]] (+) [[C, D], [-D, C]]``
    with ``D = Im(a_s a_p*)``. The 14 entries other than M23 and M32 agree
    directly. M23 and M32 have opposite signs: Mitsuba's amplitudes are the
    conjugates of ours (previous test), so its ``D`` is ``-Im(r_s r_p*)``.
    Both describe the same physical field; the difference is the meaning of
    ``S3 > 0``: Mitsuba (SPIE convention, "receiver looking at the source")
    calls it right circular = clockwise looking into the beam, whereas the
    paper's eq. (5) evaluated with Born & Wolf amplitudes makes ``S3 > 0`` a
    field turning from s toward p, counter-clockwise looking into the beam.
    Hence ``M_pihim = F M_mitsuba F`` with ``F = diag(1, 1, 1, -1)``.
    """
    ours = fresnel_reflection_mueller(c, 1.0, n)
    theirs = np.array(mi.mueller.specular_reflection(c, _eta(mi, n)), dtype=float)
    assert np.allclose(ours, FLIP_S3 @ theirs @ FLIP_S3, atol=2e-6, rtol=0)
    mask = np.ones((4, 4), bool)
    mask[2, 3] = mask[3, 2] = False
    assert np.allclose(ours[mask], theirs[mask], atol=2e-6, rtol=0)
    if abs(ours[2, 3]) > 1e-4:  # retardance present: the circular entries differ in sign only
        assert np.sign(ours[2, 3]) == -np.sign(theirs[2, 3])


@pytest.mark.parametrize("n", [1.5, 1.33, 2.4, 1.0 / 1.5], ids=str)
@pytest.mark.parametrize("c", COS)
def test_mitsuba_transmission_agrees(mi, n, c):
    """Power transmission Mueller matrix vs ``mi.mueller.specular_transmission`` (real indices)."""
    ours = fresnel_transmission_mueller(c, 1.0, n)
    theirs = np.array(mi.mueller.specular_transmission(c, n), dtype=float)
    assert np.allclose(ours, theirs, atol=3e-6, rtol=0)


def test_negative_k_is_refused_and_its_conjugate_is_physical():
    # issue 11: the n - ik form gave reflectance > 1 (1.0185 for silver-like 0.055 - 3.32i)
    with pytest.raises(PihimInputError, match="k < 0.*numpy.conj"):
        fresnel_reflection_mueller(1.0, 1.0, 0.055 - 3.32j)
    with pytest.raises(PihimInputError, match="k < 0"):
        fresnel_amplitudes(np.array([0.5, 1.0]), np.array([1.0, 1.0 - 1e-3j]), 1.5)
    m = fresnel_reflection_mueller(np.linspace(0.0, 1.0, 11), 1.0, np.conj(0.055 - 3.32j))
    assert np.all(m[..., 0, 0] <= 1.0) and np.all(m[..., 0, 0] > 0.9)


def test_brewster_angle_needs_both_indices_in_order():
    assert brewster_angle_deg(1.0, 1.5) == pytest.approx(56.3099, abs=1e-4)
    assert brewster_angle_deg(1.5, 1.0) == pytest.approx(33.6901, abs=1e-4)  # from inside the glass
    with pytest.raises(TypeError):
        brewster_angle_deg(1.5)  # type: ignore[call-arg]  # used to return 45 deg (n1 = 1.5, n2 defaulted)
    for bad in (0.0, -1.5, math.nan, 1.5 + 0.1j):
        with pytest.raises(PihimInputError, match="finite real index"):
            brewster_angle_deg(1.0, bad)
