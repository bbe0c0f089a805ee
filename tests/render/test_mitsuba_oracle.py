"""Mitsuba 3 as an oracle for the renderer: a Fresnel plane under a uniform unpolarized sky.

Set-up (identical in both renderers)
------------------------------------
One large horizontal rectangle (200 m x 200 m, front side up) whose front is
a plain dielectric interface of index n = 1.5, under a uniform, unpolarized
sky of radiance 1 and nothing else (no sun, no ground): the camera sees the
sky reflected once. A 64 x 64 pinhole camera (3.45 um pixels, 12 mm lens,
1.05 deg horizontal field of view, so every pixel sees the plane) 10 m from
the plane's centre looks at it at incidence 30 deg, at Brewster's angle
(56.31 deg) and at 70 deg, from azimuth 215 deg (South-West of the target,
so that the plane of incidence is along no axis of the field), with the
camera rolled by 0 and 30 deg so that the AoP is not trivially 0 or 90 deg.

* pihim: :func:`pihim.render.frame.render_frame` of
  ``rectangle_scene(..., kind=FACET)`` with
  ``Environment(sky=SkyModel(dmax=0, radiance="uniform"), ground=None,
  mirror=FresnelMirror(n=1.5), sun_irradiance_w_m2=0)``.
* Mitsuba 3 (``scalar_spectral_polarized``, else ``scalar_rgb_polarized``):
  ``stokes`` integrator around ``path`` with ``max_depth = 2`` (camera ray,
  one reflection, the emitter), ``constant`` emitter with a flat spectrum of
  1, ``perspective`` sensor with the same field of view (``fov_axis = x``;
  Mitsuba's film spans the pixel edges, so ``tan(fov / 2) = W / (2 fx)``
  puts its pixel centres exactly on pihim's) and
  ``to_world = look_at(C, C + forward, up = -down)`` built from the rows
  ``(right, down, forward)`` of pihim's ``CameraPose.rotation``, so that
  Mitsuba's camera up is exactly pihim's image up. The plane is a
  ``rectangle`` with a ``conductor`` BSDF of ``eta = 1.5, k = 0``: Mitsuba's
  conductor evaluates the complex Fresnel amplitudes of ``eta - ik``, which
  for ``k = 0`` are those of the dielectric interface, and it only reflects,
  like pihim's opaque facet. (A ``dielectric`` BSDF on a single rectangle
  would also let the sky through from behind; on a closed thick slab it
  gives the same polarization, checked by
  :func:`test_dielectric_slab_equals_the_conductor_stand_in`.)

Mitsuba's Stokes frame at the sensor, and the map to pihim's image frame
------------------------------------------------------------------------
From Mitsuba's source (``src/integrators/stokes.cpp`` and
``include/mitsuba/render/mueller.h``, Mitsuba 3.x): the ``stokes``
integrator takes the sub-integrator's Stokes vector, which travels along
``-ray.d`` (toward the sensor) with the implicit basis
``stokes_basis(-ray.d)``, and rotates it with
``rotate_stokes_basis(-ray.d, current, target)`` into the reference axis

    ``e_mi = normalize(ray.d x up)``, ``up = sensor.to_world * (0, 1, 0)``,

which for the central ray is image right (``forward x up = right`` in
OpenCV's right-handed (right, down, forward) frame). ``rotate_stokes_basis``
measures the angle from the current to the target axis positive when
``(current x target) . forward > 0``, ``forward`` being the propagation
direction ``-ray.d``, and applies ``rotator(theta) = [[1, 0, 0, 0],
[0, c, s, 0], [0, -s, c, 0], [0, 0, 0, 1]]`` (``c, s = cos 2 theta,
sin 2 theta``): exactly pihim's change of reference for an axis turned
counter-clockwise looking into the beam (``docs/conventions.md``). Hence
Mitsuba's ``S2 > 0`` lies along ``(e + d x e) / sqrt(2)`` with ``d`` the
light's direction of travel, as in pihim; ``mueller.h`` says the same in words
(the polarization ellipse is "observed from the view of the sensor, looking
back along the propagation direction"). Mitsuba's images are stored like
pihim's: row 0 at the top (image up), columns growing to the right
(:func:`test_mitsuba_image_orientation_matches_pihim`).

So Mitsuba's (S0, S1, S2) per pixel is pihim's image-frame Stokes vector up to
one reference-axis rotation per pixel, from ``e_mi = normalize(d x up)``
(perpendicular to the camera's up axis) to pihim's
``e_pi = normalize(right - (right . d) d)`` (image right made perpendicular
to the ray): ``S_pihim = R(t) S_mi`` with ``t`` the angle from ``e_mi`` to
``e_pi`` counter-clockwise looking into the beam
(:func:`pihim.polarimetry.frames.change_reference`). The two axes coincide on
the central row and column and differ by about ``x y`` radians at normalized
image coordinates ``(x, y)`` (here at most 0.005 deg, in the corners): at
this field of view the map is nearly the identity; it is applied anyway. No sign
changes: in particular no S2 flip. (S3, not compared here, would flip sign:
Mitsuba's circular convention is the opposite of pihim's,
``tests/surfaces/test_fresnel_oracle.py``.) Before relying on it,
:func:`test_mitsuba_frame_from_a_known_plane` checks the frame against
vector optics alone, without pihim's renderer: the reflected skylight's field
lies along the s direction ``d_in x n`` (horizontal here), which at zero roll
is image right (Mitsuba ``S1 > 0``, AoP 0), and which a camera rolled by
``+30 deg`` sees turned counter-clockwise by 30 deg (Mitsuba AoP +30 deg, not
150 deg).

Agreement reached (Mitsuba 3.9.1, ``scalar_spectral_polarized``, 16 spp
stratified, box filter; all six views): mean DoLP over the central 32 x 32
pixels within 2.2e-7 and per pixel within 4.1e-5; AoP of the mean within
1.2e-5 deg and per pixel within 1.9e-3 deg (Mitsuba's sub-pixel samples vs
pihim's pixel centre); reflectance (Mitsuba's S0 divided pixel by pixel by
its bare sky rendered with the same seed, hence the same wavelengths) within
1.2e-5 relative. The asserted tolerances (DoLP 1e-3, AoP 0.1 deg,
reflectance 1e-3) are well inside those asked of the oracle (0.01 and 1 deg)
and leave room for float32 rendering.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.polarimetry import aop_deg, aop_difference_deg, dolp
from pihim.polarimetry.frames import change_reference, normalize
from pihim.render.frame import RenderSettings, render_frame
from pihim.render.paths import MIRROR, SKY
from pihim.render.scene import FACET, rectangle_scene
from pihim.render.shading import Environment
from pihim.sky.model import SkyModel
from pihim.surfaces.fresnel import brewster_angle_deg, fresnel_reflectance
from pihim.surfaces.mirror import FresnelMirror

mitsuba = pytest.importorskip("mitsuba")

INDEX = 1.5
WIDTH = 64
FOCAL_MM = 12.0
DISTANCE_M = 10.0
CAMERA_AZIMUTH_DEG = 215.0  # seen from the target, clockwise from North
INCIDENCES_DEG = (30.0, brewster_angle_deg(1.0, INDEX), 70.0)
ROLLS_DEG = (0.0, 30.0)
SPP = 16
#: Central region used for the means (pixels).
CENTRE = slice(WIDTH // 4, 3 * WIDTH // 4)
DOLP_TOL = 1e-3
AOP_TOL_DEG = 0.1

PLANE = ([-100.0, -100.0, 0.0], [200.0, 0.0, 0.0], [0.0, 200.0, 0.0])  # origin, edge_u, edge_v: front = +z


@pytest.fixture(scope="module")
def mi():
    for variant in ("scalar_spectral_polarized", "scalar_rgb_polarized"):
        if variant in mitsuba.variants():
            mitsuba.set_variant(variant)
            return mitsuba
    pytest.skip(f"no scalar polarized Mitsuba variant installed (have {mitsuba.variants()})")


@pytest.fixture(scope="module")
def environment():
    return Environment(sun_dir=(0.0, 0.0, 1.0), sky=SkyModel(dmax=0.0, radiance="uniform"), ground=None,
                       mirror=FresnelMirror(n=INDEX), sun_irradiance_w_m2=0.0)


def _camera() -> CameraModel:
    return CameraModel(WIDTH, WIDTH, focal_length_mm=FOCAL_MM)


def _pose(incidence_deg: float, roll_deg: float) -> CameraPose:
    th, az = math.radians(incidence_deg), math.radians(CAMERA_AZIMUTH_DEG)
    toward_camera = np.array([math.sin(th) * math.sin(az), math.sin(th) * math.cos(az), math.cos(th)])
    return CameraPose.look_at(DISTANCE_M * toward_camera, [0.0, 0.0, 0.0], roll_deg=roll_deg)


def _pixel_rays_world(camera: CameraModel, pose: CameraPose) -> np.ndarray:
    """Unit world directions of the pixel-centre rays, shape (H, W, 3)."""
    jj, ii = np.meshgrid(np.arange(camera.width_px, dtype=float), np.arange(camera.height_px, dtype=float))
    return camera.pixel_rays(jj, ii) @ np.asarray(pose.rotation, float)


# ---------------------------------------------------------------------------- renderers


def _render_pihim(scene, env, camera, pose):
    fr = render_frame(scene, camera, pose, env, RenderSettings(supersample=4, max_bounces=2))
    return np.stack([fr.s0, fr.s1, fr.s2], axis=-1).astype(float), fr


def _render_mitsuba(mi, camera, pose, shape=None, *, spp=SPP, seed=0):
    """Mitsuba's Stokes image (H, W, 3) mapped into pihim's image frame (see the module notes).

    The G channel of the ``S0.* .. S2.*`` outputs is used (all three give the
    same ratios: the index does not depend on wavelength).
    """
    right, down, forward = np.asarray(pose.rotation, float)
    c = np.asarray(pose.position_m, float)
    fov_x = 2.0 * math.degrees(math.atan(0.5 * camera.width_px / camera.fx_px))
    t4 = mi.ScalarTransform4f
    desc = {
        "type": "scene",
        "integrator": {"type": "stokes", "inner": {"type": "path", "max_depth": 2}},
        "sensor": {
            "type": "perspective",
            "fov": fov_x,
            "fov_axis": "x",
            "to_world": t4().look_at(origin=c.tolist(), target=(c + forward).tolist(), up=(-down).tolist()),
            "film": {"type": "hdrfilm", "width": camera.width_px, "height": camera.height_px,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "stratified", "sample_count": spp},
        },
        "sky": {"type": "constant", "radiance": {"type": "spectrum", "value": 1.0}},
    }
    if shape is not None:
        desc["plane"] = shape
    scene = mi.load_dict(desc)
    img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=float)
    names = list(scene.integrator().aov_names())
    first = img.shape[-1] - len(names)  # the film's own channels come first
    s_mi = np.stack([img[..., first + names.index(f"S{k}.G")] for k in range(3)], axis=-1)
    # per pixel: reference axis e_mi = normalize(d x up) -> pihim's e_pi = image right perpendicular to d
    d = _pixel_rays_world(camera, pose)
    e_mi = normalize(np.cross(d, -down))
    e_pi = normalize(right - (d @ right)[..., None] * d)
    s4 = np.concatenate([s_mi, np.zeros(s_mi.shape[:-1] + (1,))], axis=-1)
    return change_reference(s4, -d, e_mi, e_pi)[..., :3]


def _plane_shape(mi, bsdf=None):
    t4 = mi.ScalarTransform4f
    return {"type": "rectangle", "to_world": t4().scale([100.0, 100.0, 1.0]),
            "bsdf": bsdf or {"type": "conductor", "eta": INDEX, "k": 0.0}}


def _mean_dolp_aop(s):
    """Mean per-pixel DoLP and the AoP of the mean normalized (S1, S2), over the central region."""
    c = s[CENTRE, CENTRE]
    p = dolp(c[..., 0], c[..., 1], c[..., 2])
    q, u = c[..., 1] / c[..., 0], c[..., 2] / c[..., 0]
    return float(np.mean(p)), float(aop_deg(np.mean(q), np.mean(u)))


# ---------------------------------------------------------------------------- Mitsuba's frame


@pytest.mark.parametrize("roll_deg", ROLLS_DEG)
@pytest.mark.parametrize("incidence_deg", INCIDENCES_DEG, ids=lambda v: f"{v:.2f}")
def test_mitsuba_frame_from_a_known_plane(mi, incidence_deg, roll_deg):
    """Mitsuba's sensor Stokes against vector optics alone (no pihim renderer).

    Unpolarized light reflected by the plane is partially polarized along the
    s direction ``d_in x n``; seen by the camera its image AoP is the angle of
    the projected s axis counter-clockwise from image right as displayed
    (``(cos a, -sin a)`` in (column, row)). DoLP is ``(R_s - R_p) / (R_s + R_p)``.
    """
    camera, pose = _camera(), _pose(incidence_deg, roll_deg)
    s = _render_mitsuba(mi, camera, pose, _plane_shape(mi))
    right, down, forward = np.asarray(pose.rotation, float)
    d_in = -(forward - 2.0 * forward[2] * np.array([0.0, 0.0, 1.0]))  # skylight reflected into the centre pixel
    s_axis = normalize(np.cross(d_in, [0.0, 0.0, 1.0]))  # s = d_in x n, perpendicular to forward
    expected_aop = math.degrees(math.atan2(-(s_axis @ down), s_axis @ right)) % 180.0
    assert expected_aop == pytest.approx(roll_deg, abs=1e-6)  # the roll turns the scene counter-clockwise
    r_s, r_p = fresnel_reflectance(math.cos(math.radians(incidence_deg)), 1.0, INDEX)
    centre = s[WIDTH // 2 - 1:WIDTH // 2 + 1, WIDTH // 2 - 1:WIDTH // 2 + 1].mean(axis=(0, 1))
    assert dolp(*centre) == pytest.approx((r_s - r_p) / (r_s + r_p), abs=DOLP_TOL)
    assert aop_difference_deg(aop_deg(centre[1], centre[2]), expected_aop) < AOP_TOL_DEG
    if roll_deg == 0.0:
        assert centre[1] > 0.0  # field along image right: Mitsuba's S1 axis is image right


def test_mitsuba_image_orientation_matches_pihim(mi, environment):
    """A quarter plane fills the upper-right image quadrant at zero roll, in both renderers, at any roll.

    The quadrant lies right of and beyond the target; Mitsuba's row 0 must be
    image up and its columns grow to the right, like pihim's. A mirrored,
    flipped or transposed mask would disagree on a sixth to a half of the
    pixels, not just along the edges.
    """
    for roll in (0.0, 30.0):
        camera, pose = _camera(), _pose(56.0, roll)
        level = _pose(56.0, 0.0).rotation
        r_h = np.asarray(level[0], float)  # horizontal image right
        far = normalize(np.asarray(level[2], float) * [1.0, 1.0, 0.0])
        edge_u, edge_v = 100.0 * r_h, 100.0 * far  # r_h x far = +z: the front faces up
        scene = rectangle_scene([[0.0, 0.0, 0.0]], [edge_u], [edge_v], FACET)
        _, fr = _render_pihim(scene, environment, camera, pose)
        mask_pi = fr.labels[..., 0] == MIRROR
        assert set(np.unique(fr.labels[..., 0])) == {MIRROR, SKY}
        t4 = mi.ScalarTransform4f
        frame = np.eye(4)
        frame[:3, 0], frame[:3, 1], frame[:3, 2] = 50.0 * r_h, 50.0 * far, [0.0, 0.0, 1.0]
        frame[:3, 3] = 50.0 * (r_h + far)  # rectangle [-1, 1]^2 -> the quadrant
        shape = {"type": "rectangle", "to_world": t4(frame.tolist()),
                 "bsdf": {"type": "conductor", "eta": INDEX, "k": 0.0}}
        s_mi = _render_mitsuba(mi, camera, pose, shape)
        mask_mi = s_mi[..., 0] < 0.5 * np.median(s_mi[..., 0])  # sky pixels are ~1, plane pixels < 0.2
        n = mask_pi.size
        assert 0.2 * n < mask_pi.sum() < 0.3 * n
        if roll == 0.0:
            assert mask_mi[2, -3] and not mask_mi[-3, 2] and not mask_mi[2, 2] and not mask_mi[-3, -3]
        assert np.count_nonzero(mask_mi != mask_pi) <= 2 * WIDTH  # only along the two edges
        for flipped in (mask_mi[:, ::-1], mask_mi[::-1, :], mask_mi.T):
            assert np.count_nonzero(flipped != mask_pi) > 8 * WIDTH


# ---------------------------------------------------------------------------- pihim vs Mitsuba


@pytest.fixture(scope="module")
def plane_scene():
    return rectangle_scene(*([v] for v in PLANE), kind=FACET)


@pytest.fixture(scope="module")
def mitsuba_sky(mi):
    """Mitsuba's S0 of the bare sky (same sampler seed: same wavelengths per pixel), for reflectances."""
    camera = _camera()
    return {incidence: _render_mitsuba(mi, camera, _pose(incidence, 0.0))[..., 0] for incidence in INCIDENCES_DEG}


@pytest.mark.parametrize("roll_deg", ROLLS_DEG)
@pytest.mark.parametrize("incidence_deg", INCIDENCES_DEG, ids=lambda v: f"{v:.2f}")
def test_pihim_matches_mitsuba(mi, environment, plane_scene, mitsuba_sky, incidence_deg, roll_deg):
    camera, pose = _camera(), _pose(incidence_deg, roll_deg)
    s_pi, fr = _render_pihim(plane_scene, environment, camera, pose)
    assert np.all(fr.labels[..., 0] == MIRROR) and np.all(fr.labels[..., 3] == SKY)
    s_mi = _render_mitsuba(mi, camera, pose, _plane_shape(mi))
    dolp_pi, aop_pi = _mean_dolp_aop(s_pi)
    dolp_mi, aop_mi = _mean_dolp_aop(s_mi)
    assert abs(dolp_pi - dolp_mi) < DOLP_TOL
    assert aop_difference_deg(aop_pi, aop_mi) < AOP_TOL_DEG
    assert aop_difference_deg(aop_pi, roll_deg) < AOP_TOL_DEG  # s is horizontal: AoP = roll
    # per pixel
    p_pi, p_mi = (dolp(s[..., 0], s[..., 1], s[..., 2]) for s in (s_pi, s_mi))
    assert np.max(np.abs(p_pi - p_mi)) < DOLP_TOL
    a_pi, a_mi = (aop_deg(s[..., 1], s[..., 2]) for s in (s_pi, s_mi))
    assert np.max(aop_difference_deg(a_pi, a_mi)) < AOP_TOL_DEG
    # reflectance: pihim's sky radiance is 1; Mitsuba's S0 divided by its bare sky, pixel by pixel
    if roll_deg == 0.0:
        refl_mi = (s_mi[..., 0] / mitsuba_sky[incidence_deg])[CENTRE, CENTRE].mean()
        assert s_pi[CENTRE, CENTRE, 0].mean() == pytest.approx(refl_mi, rel=1e-3)


def test_dielectric_slab_equals_the_conductor_stand_in(mi, environment, plane_scene):
    """Mitsuba's ``dielectric`` on a closed thick slab polarizes like the ``conductor`` with k = 0 (and pihim).

    The path tracer picks reflection or refraction at random (weight
    ``M / P``); refracted paths end inside the slab at ``max_depth = 2``,
    so the DoLP and AoP of the summed Stokes vectors are those of the
    reflection alone, whatever the sampling noise.
    """
    camera, pose = _camera(), _pose(70.0, 30.0)
    t4 = mi.ScalarTransform4f
    slab = {"type": "cube", "to_world": t4().translate([0.0, 0.0, -1.0]).scale([100.0, 100.0, 1.0]),
            "bsdf": {"type": "dielectric", "int_ior": INDEX, "ext_ior": 1.0}}
    s_slab = _render_mitsuba(mi, camera, pose, slab, spp=64)[CENTRE, CENTRE].sum(axis=(0, 1))
    s_pi = _render_pihim(plane_scene, environment, camera, pose)[0][CENTRE, CENTRE].sum(axis=(0, 1))
    assert dolp(*s_slab) == pytest.approx(dolp(*s_pi), abs=DOLP_TOL)
    assert aop_difference_deg(aop_deg(s_slab[1], s_slab[2]), aop_deg(s_pi[1], s_pi[2])) < AOP_TOL_DEG
