"""End-to-end tests of ``pihim edges`` on a small simulated frame (the Triton's field of view at 160 x 128)."""

import json
import shutil
from importlib import resources

import cv2
import jsonschema
import numpy as np
import pytest
import tifffile

from pihim.camera.model import CameraModel
from pihim.cli import main
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.render.frame import RenderSettings
from pihim.render.simulate import LookAtPose, simulate_frame, write_simulated_frame
from pihim.sky.sun import NSTTF, parse_time, sun_position

SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/edges.schema.json").read_text())
TIME = "2021-05-13T15:00-06:00"
W, H = 160, 128
TYPES = ("S0", "DoLP", "AoP", "combined")


def _expected_files(stem):
    return sorted([f"{stem}.edges.{t}.png" for t in TYPES] + [f"{stem}.gradient.{t}.tiff" for t in TYPES]
                  + [f"{stem}.edges.json"])


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """FRAME.tiff + FRAME.json (+ truth images) of 8E3 reflecting the sky."""
    field = nsttf_like_field()
    pose = track_field(field, sun_position(NSTTF, parse_time(TIME)).vector, UFACET_AIM_POINT)
    centre = pose.mirror_centres[field.index("8E3")]
    az, el = np.radians(225.0), np.radians(40.0)
    cam = centre + 40.0 * np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    sim = simulate_frame(field, TIME, camera=CameraModel(width_px=W, height_px=H, focal_length_mm=35.0 * W / 2448),
                         pose_request=LookAtPose(tuple(cam), tuple(centre)), seed=2,
                         settings=RenderSettings(supersample=1))
    out = tmp_path_factory.mktemp("frame") / "FRAME.tiff"
    write_simulated_frame(sim, out)
    return out


def _run(args, capsys):
    rc = main(["edges", *map(str, args)])
    return rc, capsys.readouterr()


def test_edges_written_with_schema_valid_summary(frame, tmp_path, capsys):
    out = tmp_path / "edges"
    rc, cap = _run([frame, "--meta", frame.with_suffix(".json"), "--out", out, "--json"], capsys)
    assert rc == 0, cap.err
    lines = cap.out.strip().splitlines()
    assert len(lines) == 1
    record = json.loads(lines[0])
    jsonschema.validate(record, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert record["schema"] == "pihim.edges/1" and record["method"] == "sobel" and record["demosaic"] == "superpixel"
    assert (record["width"], record["height"]) == (W // 2, H // 2)
    assert record["sensor"]["layout"] == "90,45,135,0" and record["sensor"]["layout_source"] == "log"
    assert sorted(p.name for p in out.iterdir()) == _expected_files("FRAME")
    on_disk = json.loads((out / "FRAME.edges.json").read_text())
    jsonschema.validate(on_disk, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert on_disk == record
    for t in TYPES:
        png = cv2.imread(str(out / f"FRAME.edges.{t}.png"), cv2.IMREAD_UNCHANGED)
        tif = tifffile.imread(out / f"FRAME.gradient.{t}.tiff")
        assert png.dtype == np.uint8 and png.shape == (H // 2, W // 2) and set(np.unique(png)) <= {0, 255}
        assert tif.dtype == np.float32 and tif.shape == (H // 2, W // 2)
        stats = record["images"][t]
        assert stats["edge_fraction"] == pytest.approx((png == 255).mean())
        assert 0.0 < stats["edge_fraction"] < 0.6
    # the heliostat's edges show up in S0 and the combined map
    assert record["images"]["combined"]["edge_fraction"] >= record["images"]["S0"]["edge_fraction"]


def test_canny_full_resolution_and_default_meta(frame, tmp_path, capsys):
    out = tmp_path / "canny"
    rc, cap = _run([frame, "--out", out, "--method", "canny", "--demosaic", "full"], capsys)
    assert rc == 0, cap.err
    assert cap.out == "" and "pihim edges" in cap.err  # human summary on stderr without --json
    record = json.loads((out / "FRAME.edges.json").read_text())
    jsonschema.validate(record, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert record["meta"] == str(frame.with_suffix(".json"))
    assert (record["width"], record["height"], record["method"]) == (W, H, "canny")
    assert tifffile.imread(out / "FRAME.gradient.DoLP.tiff").shape == (H, W)


def test_only_the_log_is_read(frame, tmp_path, capsys):
    doc = json.loads(frame.with_suffix(".json").read_text())
    for name, meta_doc in (("logonly", {"log": doc["log"]}),
                           ("badtruth", {"schema": doc["schema"], "log": doc["log"], "truth": "unreadable"}),
                           ("bare", doc["log"])):
        meta = tmp_path / f"{name}.json"
        meta.write_text(json.dumps(meta_doc))
        rc, cap = _run([frame, "--meta", meta, "--out", tmp_path / name, "--json"], capsys)
        assert rc == 0, cap.err
        got = json.loads(cap.out)
        tif = tifffile.imread(tmp_path / name / "FRAME.gradient.combined.tiff")
        ref = tifffile.imread(tmp_path / "logonly" / "FRAME.gradient.combined.tiff")
        np.testing.assert_array_equal(tif, ref)
        assert got["images"]["DoLP"]["edge_fraction"] == json.loads(
            (tmp_path / "logonly" / "FRAME.edges.json").read_text())["images"]["DoLP"]["edge_fraction"]


def _assert_bad_input(rc, cap, out, needle):
    assert rc == 2
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: ") and needle in err[0], cap.err
    assert cap.out == ""
    assert not out.exists()


def test_bad_input_one_line_exit_2_nothing_written(frame, tmp_path, capsys):
    out = tmp_path / "out"
    # a frame without metadata
    lone = tmp_path / "lone" / "LONE.tiff"
    lone.parent.mkdir()
    shutil.copy(frame, lone)
    rc, cap = _run([lone, "--out", out], capsys)
    _assert_bad_input(rc, cap, out, "no metadata")
    # metadata of another frame size
    doc = json.loads(frame.with_suffix(".json").read_text())
    doc["log"]["camera"]["width_px"] = 2 * W
    doc["log"]["camera"]["cx_px"] = (2 * W - 1) / 2
    other = tmp_path / "other.json"
    other.write_text(json.dumps(doc))
    rc, cap = _run([frame, "--meta", other, "--out", out], capsys)
    _assert_bad_input(rc, cap, out, f"describes a {2 * W}x{H} frame")
    # unreadable files
    junk = tmp_path / "junk.tiff"
    junk.write_bytes(b"not a tiff at all")
    rc, cap = _run([junk, "--meta", frame.with_suffix(".json"), "--out", out], capsys)
    _assert_bad_input(rc, cap, out, "junk.tiff")
    broken = tmp_path / "broken.json"
    broken.write_text("{\"log\": ")
    rc, cap = _run([frame, "--meta", broken, "--out", out], capsys)
    _assert_bad_input(rc, cap, out, "not valid JSON")
    nolog = tmp_path / "nolog.json"
    nolog.write_text(json.dumps({"truth": {}}))
    rc, cap = _run([frame, "--meta", nolog, "--out", out], capsys)
    _assert_bad_input(rc, cap, out, "no 'log'")
    rc, cap = _run([frame, "--meta", tmp_path / "missing.json", "--out", out], capsys)
    _assert_bad_input(rc, cap, out, "not found")
    # a sensor description of the wrong shape (an internal error once: the analyser went through dict())
    for where, value, needle in ((("sensor", "model", "analyser"), "x", "analyser must be an object"),
                                 (("sensor", "model", "analyser"), [1, 2], "analyser must be an object"),
                                 (("sensor", "model", "analyser"), {"m": 1}, "analyser: calibration JSON has no"),
                                 (("sensor",), [], "'sensor' must be an object, got list"),
                                 (("sensor", "model"), 0, "'sensor.model' must be an object, got int"),
                                 # named the file only when the frame was decoded ("bit depth 99 does not fit")
                                 (("sensor", "model", "bit_depth"), 99, "bad.json: log sensor bit_depth must be an "
                                                                       "integer from 1 to 16, got 99")):
        bad = json.loads(frame.with_suffix(".json").read_text())
        node = bad["log"]
        for key in where[:-1]:
            node = node[key]
        node[where[-1]] = value
        (tmp_path / "bad.json").write_text(json.dumps(bad))
        rc, cap = _run([frame, "--meta", tmp_path / "bad.json", "--out", out], capsys)
        _assert_bad_input(rc, cap, out, needle)
    rc, cap = _run([frame, "--out", out, "--method", "laplace"], capsys)
    _assert_bad_input(rc, cap, out, "laplace")
    rc, cap = _run([frame, "--out", out, "--demosaic", "bayer"], capsys)
    _assert_bad_input(rc, cap, out, "bayer")
    assert not out.exists()
    # an existing output folder keeps what it had, and gets nothing
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "mine.txt").write_text("x")
    rc, cap = _run([lone, "--out", keep], capsys)
    assert rc == 2 and sorted(p.name for p in keep.iterdir()) == ["mine.txt"]


def test_a_failed_write_leaves_nothing(frame, tmp_path, capsys, monkeypatch):
    calls = {"n": 0}
    real = tifffile.imwrite  # the command imports tifffile where it writes: patched there

    def flaky(path, data, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk full")
        return real(path, data, *a, **k)

    monkeypatch.setattr(tifffile, "imwrite", flaky)
    out = tmp_path / "flaky"
    rc, cap = _run([frame, "--out", out], capsys)
    assert rc == 1 and "disk full" in cap.err and cap.err.startswith("pihim: error: ")
    assert not out.exists()
    keep = tmp_path / "keep"
    keep.mkdir()
    calls["n"] = 0
    rc, cap = _run([frame, "--out", keep], capsys)
    assert rc == 1 and list(keep.iterdir()) == []


def test_a_lucid_raw_buffer_is_sized_by_the_log(frame, tmp_path, capsys):
    buf = tmp_path / "FRAME.raw"
    tifffile.imread(frame).astype("<u2").tofile(buf)  # PolarizeMono16
    shutil.copy(frame.with_suffix(".json"), tmp_path / "FRAME.json")
    rc, cap = _run([buf, "--out", tmp_path / "raw"], capsys)
    assert rc == 0, cap.err
    rc, cap = _run([frame, "--out", tmp_path / "tiff"], capsys)
    assert rc == 0, cap.err
    for t in TYPES:
        np.testing.assert_array_equal(tifffile.imread(tmp_path / "raw" / f"FRAME.gradient.{t}.tiff"),
                                      tifffile.imread(tmp_path / "tiff" / f"FRAME.gradient.{t}.tiff"))


def test_noise_weighting_by_the_logs_sensor_and_without_it(frame, tmp_path, capsys):
    from pihim.camera import polar_image
    from pihim.inspection.edges import edge_maps, noise_sigmas

    doc = json.loads(frame.with_suffix(".json").read_text())
    model = doc["log"]["sensor"]["model"]
    pim = polar_image(tifffile.imread(frame), demosaic="superpixel", bit_depth=12)
    records = {}
    for flag, noise in (("--noise-weighted", noise_sigmas(pim.s0, electrons_per_dn=model["electrons_per_dn"],
                                                          read_noise_dn=model["read_noise_dn"])),
                        ("--no-noise-weighted", None)):
        out = tmp_path / flag
        rc, cap = _run([frame, "--out", out, flag, "--json"], capsys)
        assert rc == 0, cap.err
        records[flag] = json.loads(cap.out)
        want = edge_maps(pim.s0, pim.dolp, pim.aop_deg, "sobel", noise=noise)
        for t in TYPES:
            np.testing.assert_array_equal(tifffile.imread(out / f"FRAME.gradient.{t}.tiff"), want[t].gradient)
    assert records["--noise-weighted"]["parameters"]["noise_weighted"] is True
    assert records["--noise-weighted"]["noise_model"] == {"electrons_per_dn": model["electrons_per_dn"],
                                                          "read_noise_dn": model["read_noise_dn"]}
    assert records["--no-noise-weighted"]["parameters"]["noise_weighted"] is False
    assert records["--no-noise-weighted"]["noise_model"] is None
    for rec in records.values():
        jsonschema.validate(rec, SCHEMA, cls=jsonschema.Draft202012Validator)
    # the default is noise-weighted
    rc, cap = _run([frame, "--out", tmp_path / "default", "--json"], capsys)
    assert rc == 0 and json.loads(cap.out)["parameters"] == records["--noise-weighted"]["parameters"]
    # a malformed noise model in the log: one line, exit 2
    doc["log"]["sensor"]["model"]["electrons_per_dn"] = -1.0
    meta = tmp_path / "bad.json"
    meta.write_text(json.dumps(doc))
    rc, cap = _run([frame, "--meta", meta, "--out", tmp_path / "bad"], capsys)
    assert rc == 2 and cap.err.count("\n") == 1 and "electrons_per_dn" in cap.err
