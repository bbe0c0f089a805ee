"""Tests of :mod:`pihim.inspection.success`: the paper's edge-detection success, scored against the truth.

One small rendered frame (the Triton's field of view at 320 x 256 pixels): the
heliostat 8E3 tracking at 15:00 on 2021-05-13, seen from 40 m at 40 deg
elevation from the south-west of its mirror, so that every one of its 25
facets reflects the sky (a DoLP around 0.5) -- the sky-reflection case of the
paper's section 4.1. Facet edges are then DoLP edges: against the facet gaps
and the ground. Canting errors are on (2 mrad) so that the true facets are
not the design ones.
"""

import json

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.inspection.edges import edge_maps
from pihim.inspection.success import (
    EDGE_NAMES,
    EdgeSuccess,
    FacetOutlines,
    FrameScore,
    edge_success,
    facet_outlines_px,
    outlines_from_simulation,
    outlines_from_truth,
    score_frame,
    success_rate,
)
from pihim.polarimetry.stokes import aop_deg, dolp
from pihim.render.frame import RenderSettings
from pihim.render.paths import MIRROR, SKY
from pihim.render.simulate import LookAtPose, simulate_frame
from pihim.sky.sun import NSTTF, parse_time, sun_position

TIME = "2021-05-13T15:00-06:00"
W, H = 320, 256


@pytest.fixture(scope="module")
def frame():
    field = nsttf_like_field()
    pose = track_field(field, sun_position(NSTTF, parse_time(TIME)).vector, UFACET_AIM_POINT)
    i = field.index("8E3")
    centre = pose.mirror_centres[i]
    az, el = np.radians(225.0), np.radians(40.0)
    camera_m = centre + 40.0 * np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    sim = simulate_frame(field, TIME, camera=CameraModel(width_px=W, height_px=H, focal_length_mm=35.0 * W / 2448),
                         pose_request=LookAtPose(tuple(camera_m), tuple(centre)), canting_sigma_mrad=2.0, seed=3,
                         settings=RenderSettings(supersample=3))
    r = sim.rendered
    with np.errstate(invalid="ignore", divide="ignore"):
        d = dolp(r.s0.astype(float), r.s1, r.s2)
        a = aop_deg(r.s1.astype(float), r.s2)
    return {"sim": sim, "index": i, "s0": r.s0, "dolp": d, "aop": a, "labels": r.labels,
            "outlines": outlines_from_simulation(sim, "8E3")}


def test_the_frame_is_the_intended_sky_reflection(frame):
    lab, i = frame["labels"], frame["index"]
    hua = (lab[..., 0] == MIRROR) & (lab[..., 1] == i)
    assert hua.sum() > 0.1 * W * H
    assert np.all(lab[..., 3][hua] == SKY)  # every HUA mirror pixel reflects the sky
    assert np.median(frame["dolp"][hua]) > 0.4
    assert set(np.unique(lab[..., 2][hua])) == set(range(1, 26))


def test_outlines_follow_the_labelled_facets(frame):
    out = frame["outlines"]
    assert isinstance(out, FacetOutlines)
    assert out.points_px.shape[:2] == (25, 4) and out.image_size == (W, H) and out.heliostat == frame["index"]
    np.testing.assert_array_equal(out.facet_ids, np.arange(1, 26))
    # samples are about a pixel apart, and the outline ends where it began
    assert 0.3 < np.nanmax(out.step_px) <= 1.0
    np.testing.assert_allclose(out.points_px[:, :, 0], out.corners_px, atol=1e-9)
    np.testing.assert_allclose(out.points_px[:, :, -1], np.roll(out.corners_px, -1, axis=1), atol=1e-9)
    # just inside each facet (towards its centre) the labels show that facet
    lab = frame["labels"]
    centre = out.corners_px.mean(axis=1)[:, None, None, :]
    inner = out.points_px[:, :, 2:-2] + 1.0 * (centre - out.points_px[:, :, 2:-2]) / np.linalg.norm(
        centre - out.points_px[:, :, 2:-2], axis=-1, keepdims=True)
    u = np.rint(inner[..., 0]).astype(int)
    v = np.rint(inner[..., 1]).astype(int)
    ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    same = (lab[v[ok], u[ok], 1] == frame["index"]) & (lab[v[ok], u[ok], 2] == np.broadcast_to(
        out.facet_ids[:, None, None], u.shape)[ok])
    assert same.mean() > 0.98
    # rebuilt from the JSON document's truth, the outlines are the same
    doc = json.loads(json.dumps(frame["sim"].document()))
    again = outlines_from_truth(doc, "8E3")
    np.testing.assert_allclose(again.points_px, out.points_px, atol=1e-6)
    assert again.heliostat == out.heliostat
    with pytest.raises(PihimInputError):
        outlines_from_truth({"log": {}}, "8E3")


@pytest.mark.parametrize("method", ["sobel", "canny"])
def test_dolp_edges_find_every_facet_edge(frame, method):
    maps = edge_maps(frame["s0"], frame["dolp"], frame["aop"], method)
    res = edge_success(maps["DoLP"].edges, frame["outlines"], k_px=2.0, min_coverage=0.9, labels=frame["labels"])
    assert isinstance(res, EdgeSuccess)
    assert res.success, res.failed
    assert res.n_judged >= 90  # nearly all 100 facet edges are in view
    assert res.min_edge_coverage >= 0.9 and res.failed == []
    assert res.coverage.shape == (25, 4) and np.all(np.isnan(res.coverage[~res.judged]))
    d = res.to_dict()
    assert d["success"] is True and d["edges_judged"] == res.n_judged


def test_emptied_or_misplaced_edge_maps_fail(frame):
    out, lab = frame["outlines"], frame["labels"]
    empty = np.zeros((H, W), bool)
    res = edge_success(empty, out, labels=lab)
    assert not res.success and res.n_judged >= 90
    assert np.all(res.coverage[res.judged] == 0.0) and len(res.failed) == res.n_judged
    # the right edges, 5 px off: beyond k = 2 px on the edges across the shift
    edges = edge_maps(frame["s0"], frame["dolp"], frame["aop"], "canny")["DoLP"].edges
    shifted = np.zeros_like(edges)
    shifted[:, 5:] = edges[:, :-5]
    res = edge_success(shifted, out, labels=lab)
    assert not res.success
    assert res.min_edge_coverage < 0.5
    # ... but inside a 6 px tolerance
    assert edge_success(shifted, out, k_px=6.0, labels=lab).success
    # one facet's edges erased: exactly that facet (and the edges it shares gaps with, if any) fails
    blank = edges.copy()
    c = out.corners_px[12]
    u0, v0 = np.floor(c.min(axis=0)).astype(int) - 3
    u1, v1 = np.ceil(c.max(axis=0)).astype(int) + 3
    blank[max(v0, 0):v1, max(u0, 0):u1] = False
    res = edge_success(blank, out, labels=lab)
    assert not res.success and 13 in {f for f, _ in res.failed}


def test_hidden_edges_are_not_asked_for(frame):
    out, lab, i = frame["outlines"], frame["labels"], frame["index"]
    edges = edge_maps(frame["s0"], frame["dolp"], frame["aop"])["DoLP"].edges
    # hide the centre facet (13) behind an occluder: relabel its pixels, erase its edges
    c = out.corners_px[12]
    u0, v0 = np.floor(c.min(axis=0)).astype(int) - 3
    u1, v1 = np.ceil(c.max(axis=0)).astype(int) + 3
    occluded = lab.copy()
    occluded[v0:v1, u0:u1, 1] = i + 1  # another heliostat in front
    blank = edges.copy()
    blank[v0:v1, u0:u1] = False
    res = edge_success(blank, out, labels=occluded)
    assert not res.judged[12].any() and res.success
    # without labels the same edges count (they are in the image): failure
    assert not edge_success(blank, out).success
    # edges outside the image are never judged: the left half of the frame, as a camera of its own
    full = edge_success(edges, out, labels=lab)
    sim = frame["sim"]
    half_camera = CameraModel(width_px=W // 2, height_px=H, focal_length_mm=35.0 * W / 2448,
                              principal_point_px=((W - 1) / 2, (H - 1) / 2))
    half_out = facet_outlines_px(half_camera, sim.camera_pose,
                                 sim.true_field.facet_corners(sim.facet_normals_local)[i], heliostat=i)
    left = edge_success(edges[:, : W // 2], half_out, labels=np.ascontiguousarray(lab[:, : W // 2]))
    assert left.success and 0 < left.n_judged < full.n_judged

def test_half_resolution_edge_maps_are_scored_in_their_own_pixels(frame):
    def half(img):
        return img.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3))

    s0 = half(frame["s0"])
    with np.errstate(invalid="ignore"):
        sim = frame["sim"].rendered
        s1, s2 = half(sim.s1), half(sim.s2)
        d = np.sqrt(s1**2 + s2**2) / s0
        a = np.mod(0.5 * np.degrees(np.arctan2(s2, s1)), 180.0)
    maps = edge_maps(s0, d, a)
    res = edge_success(maps["DoLP"].edges, frame["outlines"], k_px=2.0, labels=frame["labels"])
    assert res.success, res.failed
    # the same map read as if it were full resolution is wrong everywhere
    padded = np.zeros((H, W), bool)
    padded[: H // 2, : W // 2] = maps["DoLP"].edges
    assert not edge_success(padded, frame["outlines"], labels=frame["labels"]).success
    with pytest.raises(PihimInputError, match="integer factor"):
        edge_success(np.zeros((100, 100), bool), frame["outlines"])


def test_success_rate_over_a_set(frame):
    maps = edge_maps(frame["s0"], frame["dolp"], frame["aop"])
    good = score_frame(maps, frame["outlines"], labels=frame["labels"], name="good")
    assert isinstance(good, FrameScore) and set(good.results) == {"S0", "DoLP", "AoP", "combined"}
    assert good["dolp"].success
    empty = {"DoLP": edge_success(np.zeros((H, W), bool), frame["outlines"], labels=frame["labels"])}
    rate = success_rate([good, good, empty, {"dolp": True}], "DoLP")
    assert (rate.successful, rate.unsuccessful, rate.total) == (3, 1, 4)
    assert rate.rate == pytest.approx(0.75)
    assert rate.to_dict()["success_rate"] == pytest.approx(0.75)
    assert np.isnan(success_rate([], "AoP").rate)
    with pytest.raises(PihimInputError, match="no result for image type 'AoP'"):  # was a bare KeyError
        success_rate([{"S0": True}], "AoP")
    with pytest.raises(PihimInputError, match="a verdict must be an EdgeSuccess or a bool, got 'False'"):
        success_rate([{"S0": "False"}], "S0")  # bool("False") counted as a success
    assert success_rate([{"S0": np.bool_(False)}], "S0").unsuccessful == 1


def test_bad_arguments(frame):
    out = frame["outlines"]
    with pytest.raises(PihimInputError):
        edge_success(np.zeros((H, W), bool), out, min_coverage=1.5)
    with pytest.raises(PihimInputError):
        edge_success(np.zeros((H, W), bool), out, labels=np.zeros((H, W), np.int32))
    with pytest.raises(PihimInputError):
        edge_success(np.zeros((H, W), bool), "not outlines")  # type: ignore[arg-type]
    with pytest.raises(PihimInputError):
        facet_outlines_px(CameraModel(), frame["sim"].camera_pose, np.zeros((3, 3)))
    assert EDGE_NAMES == ("top", "right", "bottom", "left")
