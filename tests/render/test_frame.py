"""The renderer against independent oracles: vector optics, OpenCV projection, exact pixel coverage.

Every expected value here is computed without the renderer's kernel: sky
Stokes from the sky model evaluated directly, reflections with
:func:`pihim.polarimetry.reflection.reflect_stokes`, positions with
:func:`pihim.camera.pose.project_points` (held to ``cv2.projectPoints`` in
tests/camera), pixel membership with ``cv2.pointPolygonTest`` and coverage
by exact polygon clipping.
"""

import math

import cv2
import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.errors import PihimInputError
from pihim.field import UFACET_AIM_POINT, apply_canting_deviation, nsttf_like_field, track_field
from pihim.planning.pipeline import build_plan
from pihim.polarimetry.frames import change_reference, normalize
from pihim.polarimetry.reflection import reflect_stokes
from pihim.polarimetry.stokes import aop_deg
from pihim.render.frame import RenderSettings, render_frame
from pihim.render.paths import MIRROR, SKY, STRUCTURE_HIT, trace_paths
from pihim.render.scene import FACET, STRUCTURE, field_scene, rectangle_scene
from pihim.render.shading import Environment, GroundTable, MirrorTable, SurfaceFinish, shade_paths
from pihim.sky.model import SkyModel
from pihim.sky.sun import NSTTF, parse_time, sun_position
from pihim.surfaces.mirror import SecondSurfaceMirror

SUN = normalize(np.array([0.5, -0.3, 0.8]))


def _square(centre, normal, size, up=(0.0, 0.0, 1.0)):
    """A square rectangle (origin, u, v) around ``centre`` whose front faces ``normal``."""
    n = normalize(np.asarray(normal, float))
    x = normalize(np.cross(up, n)) if abs(np.dot(up, n)) < 0.999 else np.array([1.0, 0.0, 0.0])
    y = np.cross(n, x)
    u, v = size * x, size * y
    return np.asarray(centre, float) - 0.5 * (u + v), u, v


def _sky_env(**kw):
    sky = SkyModel(kind="rayleigh", dmax=0.8)
    return Environment(SUN, sky, None, kw.pop("mirror", SecondSurfaceMirror()), **kw)


def test_flat_mirror_returns_the_reflected_sky_through_the_mirror_model():
    n = normalize(np.array([0.1, -0.6, 1.0]))
    o, u, v = _square([0.0, 0.0, 0.0], n, 20.0)
    scene = rectangle_scene(o[None], u[None], v[None], FACET)
    env = _sky_env()
    cam = CameraModel(width_px=65, height_px=49, focal_length_mm=20.0)
    pose = CameraPose.look_at([2.0, -12.0, 9.0], [0.0, 0.0, 0.0], roll_deg=17.0)
    frame = render_frame(scene, cam, pose, env, RenderSettings(supersample=1))
    # the centre pixel's ray is the optical axis (odd sizes, principal point at the centre)
    r0 = pose.forward
    r1 = r0 - 2 * np.dot(r0, n) * n
    s_sky, e_sky = env.sky.stokes(r1, env.sun_dir)
    s_ref, d_out, e_out = reflect_stokes(s_sky, -r1, e_sky, n, env.mirror.mueller)
    np.testing.assert_allclose(d_out, -r0, atol=1e-12)
    e_img = normalize(pose.right - np.dot(pose.right, d_out) * d_out)
    expected = change_reference(s_ref, d_out, e_out, e_img)[:3]
    got = np.array([frame.s0[24, 32], frame.s1[24, 32], frame.s2[24, 32]])
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-3 * expected[0])
    assert frame.labels[24, 32, 0] == MIRROR and frame.labels[24, 32, 3] == SKY
    # and the mirror really changes the light: reflectance ~0.95, DoLP changed by the Fresnel factors
    assert 0.9 < got[0] / s_sky[0] < 1.0


def test_camera_roll_raises_aop_by_the_roll():
    far = _square([0.0, 500.0, -50.0], [0, -1, 0], 1.0)
    scene = rectangle_scene(far[0][None], far[1][None], far[2][None], STRUCTURE)
    env = _sky_env()
    cam = CameraModel(width_px=33, height_px=33, focal_length_mm=50.0)
    target = np.array([-40.0, -30.0, 60.0])  # a bright, strongly polarized patch of sky (about 90 deg from the sun)
    aops = []
    for roll in (0.0, 25.0, -60.0):
        pose = CameraPose.look_at([0.0, 0.0, 0.0], target, roll_deg=roll)
        fr = render_frame(scene, cam, pose, env, RenderSettings(supersample=1))
        aops.append(float(aop_deg(fr.s1[16, 16], fr.s2[16, 16])))
    assert np.all(np.isfinite(aops))
    assert float(np.mod(aops[1] - aops[0], 180.0)) == pytest.approx(25.0, abs=0.05)
    assert float(np.mod(aops[2] - aops[0], 180.0)) == pytest.approx(120.0, abs=0.05)  # -60 mod 180


def _heliostat_view(distortion=(0.0, 0.0, 0.0, 0.0, 0.0)):
    field = nsttf_like_field()
    pose = track_field(field, SUN)
    i = field.index("8E3")
    centre = pose.mirror_centres[i]
    cam_pos = centre + 24.0 * pose.normals[i] + np.array([0.0, 0.0, 1.0])
    cam = CameraModel(width_px=401, height_px=361, focal_length_mm=3.9, distortion=distortion)
    return field, pose, i, cam, CameraPose.look_at(cam_pos, centre, roll_deg=8.0)


@pytest.mark.parametrize("distortion", [(0.0, 0.0, 0.0, 0.0, 0.0), (-0.08, 0.02, 1e-3, -5e-4, 0.0)])
def test_projected_facet_corners_bound_the_labelled_facets(distortion):
    field, pose, i, cam, cp = _heliostat_view(distortion)
    scene = field_scene(pose)
    env = Environment.clear_sky(SUN)
    fr = render_frame(scene, cam, cp, env, RenderSettings(supersample=1))
    corners = pose.facet_corners()[i]  # (F, 4, 3), design canting
    jj, ii = np.meshgrid(np.arange(cam.width_px, dtype=float), np.arange(cam.height_px, dtype=float))
    centres = np.column_stack([jj.ravel(), ii.ravel()])
    inside_any = np.zeros(len(centres), bool)
    direct_h = fr.labels[..., 1].ravel()
    direct_f = fr.labels[..., 2].ravel()
    direct_k = fr.labels[..., 0].ravel()
    checked = 0
    for f in range(corners.shape[0]):
        # project densely along the edges: with distortion the facet outline is slightly curved
        t = np.linspace(0.0, 1.0, 40, endpoint=False)[:, None]
        ring = np.concatenate([corners[f, k] + t * (corners[f, (k + 1) % 4] - corners[f, k]) for k in range(4)])
        poly = project_points(cam, cp, ring).astype(np.float32).reshape(-1, 1, 2)
        # signed distance of every pixel centre to the outline; those more than 1 px outside its bounding box are
        # farther than 0.05 px from it and need no test
        lo, hi = poly.reshape(-1, 2).min(axis=0) - 1.0, poly.reshape(-1, 2).max(axis=0) + 1.0
        near = np.flatnonzero(np.all((centres >= lo) & (centres <= hi), axis=1))
        dist = np.full(len(centres), -np.inf)
        dist[near] = [cv2.pointPolygonTest(poly, (float(x), float(y)), True) for x, y in centres[near]]
        inside = dist > 0.05
        inside_any |= dist > -0.05
        assert inside.sum() > 50
        assert np.all(direct_k[inside] == MIRROR)
        assert np.all(direct_h[inside] == i)
        assert np.all(direct_f[inside] == f + 1)
        checked += inside.sum()
    # no pixel centre outside every projected facet (by more than 0.05 px) is labelled a mirror of 8E3
    stray = (~inside_any) & (direct_h == i) & (direct_k == MIRROR)
    assert not np.any(stray)
    assert checked > 0.3 * cam.width_px * cam.height_px


def _coverage(poly, j, i):
    """Exact area of pixel [j-0.5, j+0.5] x [i-0.5, i+0.5] inside a convex polygon (Sutherland-Hodgman)."""
    pts = [tuple(p) for p in poly]
    for axis, bound, keep_less in ((0, j - 0.5, False), (0, j + 0.5, True), (1, i - 0.5, False), (1, i + 0.5, True)):
        out = []
        for k in range(len(pts)):
            a, b = pts[k], pts[(k + 1) % len(pts)]
            ina = a[axis] <= bound if keep_less else a[axis] >= bound
            inb = b[axis] <= bound if keep_less else b[axis] >= bound
            if ina:
                out.append(a)
            if ina != inb:
                s = (bound - a[axis]) / (b[axis] - a[axis])
                out.append((a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1])))
        pts = out
        if not pts:
            return 0.0
    x = np.array([p[0] for p in pts])
    y = np.array([p[1] for p in pts])
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_antialiased_edges_match_exact_pixel_coverage():
    # a lambertian plate (uniform S0 under a uniform sky, no sun) against the uniform sky
    n = normalize(np.array([0.0, -1.0, 0.3]))
    o, u, v = _square([0.0, 0.0, 0.0], n, 2.0, up=(0.3, 0.0, 1.0))
    scene = rectangle_scene(o[None], u[None], v[None], STRUCTURE)
    sky = SkyModel(dmax=0.0, radiance="uniform", scale=10.0)
    env = Environment(SUN, sky, None, SecondSurfaceMirror(), sun_irradiance_w_m2=0.0,
                      structure=SurfaceFinish(albedo=0.9))
    cam = CameraModel(width_px=64, height_px=56, focal_length_mm=0.75)
    pose = CameraPose.look_at(n * 12.0, [0.05, 0.0, 0.03], roll_deg=11.0)
    fr = render_frame(scene, cam, pose, env, RenderSettings(supersample=8))
    s_sky = fr.s0[0, 0]
    poly = project_points(cam, pose, np.array([o, o + u, o + u + v, o + v]))
    inside = fr.labels[..., 0] == STRUCTURE_HIT
    s_plate = float(np.median(fr.s0[inside & ~fr.supersampled]))
    assert abs(s_plate - s_sky) > 0.3 * s_sky  # a real contrast
    errs = []
    for i, j in zip(*np.nonzero(fr.supersampled)):
        f = _coverage(poly, j, i)
        errs.append((fr.s0[i, j] - (f * s_plate + (1 - f) * s_sky)) / (s_plate - s_sky))
    errs = np.abs(errs)
    assert len(errs) > 100
    assert errs.max() < 0.07  # at most about half a sample column of 8
    assert errs.mean() < 0.01


def test_one_mrad_of_canting_moves_the_reflection_as_geometric_optics_predicts():
    field = nsttf_like_field()
    time = parse_time("2021-05-13T13:00-06:00")
    sun = sun_position(NSTTF, time).vector
    plan = build_plan(field, time, NSTTF, aim_point=UFACET_AIM_POINT, heliostats=["8E3"], shift=False)
    wp = next(p.waypoints[q.waypoint_index] for p in plan.passes for q in p.predictions
              if (q.hua, q.target) == ("8E3", "7E3"))
    pose = track_field(field, sun, UFACET_AIM_POINT)
    h = field.index("8E3")
    f13 = 12
    centre = pose.facet_centres[h, f13]
    cam_pos = np.array([wp.x_m, wp.y_m, wp.z_m])
    cp = CameraPose.look_at(cam_pos, centre)
    env = Environment.clear_sky(sun)
    # the 35 mm Triton, cropped to 192 x 192 px around facet 13's centre (the facet spans ~500 px)
    cam = CameraModel(width_px=192, height_px=192)
    normals = pose.facet_normals_local.copy()
    images = []
    for el_mrad in (0.0, 1.0):
        normals[h, f13] = apply_canting_deviation(pose.facet_normals_local[h, f13], 0.0, el_mrad)
        fr = render_frame(field_scene(pose, normals), cam, cp, env, RenderSettings(supersample=2))
        assert np.all(fr.labels[..., 1] == h) and np.all(fr.labels[..., 2] == f13 + 1)
        assert np.mean(fr.labels[..., 4] == field.index("7E3")) > 0.3  # the target's back is reflected
        images.append(np.log(np.maximum(fr.s0.astype(np.float64), 1e-6)))
    win = cv2.createHanningWindow((192, 192), cv2.CV_64F)
    (dx, dy), response = cv2.phaseCorrelate(images[0], images[1], win)
    assert response > 0.2
    # prediction: the virtual image of the point the centre ray sees, mirrored in the facet plane before/after
    r0 = cp.forward
    n0 = pose.rotations[h] @ pose.facet_normals_local[h, f13]
    n1 = pose.rotations[h] @ apply_canting_deviation(pose.facet_normals_local[h, f13], 0.0, 1.0)
    hit = cam_pos + np.dot(centre - cam_pos, n0) / np.dot(r0, n0) * r0
    r1 = r0 - 2 * np.dot(r0, n0) * n0
    paths = trace_paths(field_scene(pose), hit[None] + 1e-6 * r1, r1[None], sun, max_bounces=0)
    p_obj = paths.terminal_point[0]
    assert np.all(np.isfinite(p_obj)) and 3.0 < np.linalg.norm(p_obj - hit) < 60.0
    virt = [p_obj - 2 * np.dot(p_obj - centre, n) * n for n in (n0, n1)]
    uv = project_points(cam, cp, np.array(virt))
    expected = uv[1] - uv[0]
    assert np.linalg.norm(expected) > 2.0  # ~ 2 mrad * f * L_obj / (L_cam + L_obj)
    np.testing.assert_allclose([dx, dy], expected, atol=0.05 * np.linalg.norm(expected) + 0.05)


def test_kernel_agrees_with_the_numpy_reference_path():
    field, pose, i, cam, cp = _heliostat_view()
    scene = field_scene(pose)
    env = Environment.clear_sky(SUN)
    cam = CameraModel(width_px=120, height_px=96, focal_length_mm=1.4)
    fr = render_frame(scene, cam, cp, env, RenderSettings(supersample=1))
    u = np.tile(np.arange(cam.width_px, dtype=float), cam.height_px)
    v = np.repeat(np.arange(cam.height_px, dtype=float), cam.width_px)
    d = cam.pixel_rays(u, v) @ cp.rotation
    paths = trace_paths(scene, np.broadcast_to(cp.position_m, d.shape), d, env.sun_dir)
    ref = shade_paths(paths, env, cp.right)
    got = np.column_stack([fr.s0.ravel(), fr.s1.ravel(), fr.s2.ravel()])
    np.testing.assert_array_equal(fr.labels[..., 0].ravel(), paths.first_kind)
    np.testing.assert_array_equal(fr.labels[..., 6].ravel(), paths.n_bounces)
    scale = np.maximum(ref[:, :1], 1e-9)
    assert np.max(np.abs(got - ref) / scale) < 5e-3  # sky and ground tables vs direct evaluation
    assert np.median(np.abs(got - ref) / scale) < 1e-5


def test_bad_geometry_and_light_refused():
    field, pose, i, cam, cp = _heliostat_view()
    scene = field_scene(pose)
    below = CameraPose.look_at([0.0, 50.0, -5.0], [0.0, 60.0, 0.0])
    with pytest.raises(PihimInputError, match="below the ground"):
        render_frame(scene, cam, below, Environment.clear_sky(SUN))
    with pytest.raises(PihimInputError, match="horizon"):
        Environment.clear_sky([0.3, 0.2, -0.1])
    with pytest.raises(PihimInputError):
        RenderSettings(supersample=0)


def test_sun_disc_radiance_and_size():
    env = _sky_env()
    far = _square([0.0, 500.0, -50.0], [0, -1, 0], 1.0)
    scene = rectangle_scene(far[0][None], far[1][None], far[2][None], STRUCTURE)
    cam = CameraModel(width_px=65, height_px=65, focal_length_mm=10.0)
    fr = render_frame(scene, cam, CameraPose.look_at([0, 0, 0], SUN), env, RenderSettings(supersample=1))
    sun_px = fr.labels[..., 0] == 1
    # the disc is 2 * 0.2666 deg across: its area in pixels is pi r^2 with r = f tan(0.2666 deg)
    r_px = cam.fx_px * math.tan(math.radians(env.sun_half_angle_deg))
    assert sun_px.sum() == pytest.approx(math.pi * r_px**2, rel=0.02)
    assert fr.s0[32, 32] == pytest.approx(env.sun_radiance, rel=1e-3)


def test_ground_and_mirror_tables_match_direct_evaluation():
    env = Environment.clear_sky(SUN)
    gt = GroundTable(env)
    rng = np.random.default_rng(5)
    v = normalize(rng.normal(size=(400, 3)) * [1, 1, 0.6] + [0, 0, 0.8])
    v = v[v[:, 2] > 0.15]  # views from 0 to ~80 deg zenith
    vis = rng.random(len(v)) < 0.5
    got, e = gt.lookup(v, vis)
    sun_part, _ = env.ground.stokes(v, env.sun_dir, None, e)
    everything, _ = env.ground.stokes(v, env.sun_dir, env.sky, e)
    expected = everything - sun_part + vis[:, None] * sun_part
    err = np.abs(got - expected)[:, :3] / expected[:, :1]
    assert err.max() < 2e-3
    mt = MirrorTable(env.mirror)
    c = rng.random(200)
    np.testing.assert_allclose(mt.mueller(c), env.mirror.mueller(c), atol=1e-6)


def test_rising_rays_see_the_sky_over_a_rising_ground():
    # a plane rising eastward (as the NSTTF ground does) must not catch rays that go up
    far = _square([0.0, 500.0, -50.0], [0, -1, 0], 1.0)
    scene = rectangle_scene(far[0][None], far[1][None], far[2][None], STRUCTURE, ground=(-0.3, 0.02, 0.005))
    env = Environment.clear_sky(SUN)
    cam = CameraModel(width_px=31, height_px=31, focal_length_mm=20.0)
    # looking East, 0.05 deg above the horizon: every ray rises, the plane rises faster
    pose = CameraPose.from_attitude([0.0, 0.0, 2.0], 90.0, 0.3)
    fr = render_frame(scene, cam, pose, env, RenderSettings(supersample=1))
    up = cam.pixel_rays(np.arange(31.0), np.zeros(31) + 15.0) @ pose.rotation
    assert np.all(up[:, 2] > 0)
    assert np.all(fr.labels[15, :, 0] == SKY)
    assert np.all(fr.s0[15] > 0)
    # and looking down the same plane is ground
    down = render_frame(scene, cam, CameraPose.from_attitude([0.0, 0.0, 2.0], 90.0, -30.0), env,
                        RenderSettings(supersample=1))
    assert np.all(down.labels[..., 0] == 2)


def test_clear_sky_defaults_to_the_second_surface_mirror():
    """Pinned convention: rendered heliostats are second-surface silvered glass unless told otherwise."""
    mirror = Environment.clear_sky(SUN).mirror
    assert isinstance(mirror, SecondSurfaceMirror)
    assert float(mirror.mueller(1.0)[0, 0]) == pytest.approx(0.9680, abs=5e-4)  # glass + silver at 550 nm
