"""End-to-end tests of ``pihim calibrate-camera`` on rendered chessboard frames with a known camera.

The frames are what the Triton would record of a 9x6 board (25 mm squares):
12-bit DoFP mosaics with shot and read noise, rendered by
``pihim.render.checkerboard`` through a known lens (816 x 682 px of 3.45 um,
12 mm, k1 = -0.12, principal point off centre). The tolerances and their
justification are those of tests/inspection/test_calibration.py (fx, fy
0.5 %, cx, cy 3 px, k1 0.03 with all five coefficients free, 0.02 with k3
fixed).
"""

from __future__ import annotations

import json
from importlib import resources

import cv2
import jsonschema
import numpy as np
import pytest
import tifffile

from pihim.camera import CameraModel, polar_image
from pihim.cli import main
from pihim.render.checkerboard import board_view_pose, render_checkerboard
from pihim.render.sensor import SensorModel

TRUE = CameraModel(width_px=816, height_px=682, pixel_size_um=3.45, focal_length_mm=12.0,
                   principal_point_px=(411.3, 338.1), distortion=(-0.12, 0.05, 5e-4, -3e-4, 0.0))
SQUARE = 0.025
#: (yaw, pitch, roll) deg and distance m of each view; the closest distance at which the whole board fits
VIEWS = [(0, 0, 0, 1.12), (40, 0, 5, 1.09), (-40, 0, -5, 1.09), (0, 35, 5, 1.22), (0, -35, -5, 1.22),
         (30, 30, 10, 1.11), (-30, 30, -10, 1.13), (30, -30, -10, 1.11), (-30, -30, 10, 1.13),
         (45, 15, 0, 1.21), (-45, -15, 0, 1.19), (15, -45, 0, 1.14)]
SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/camera.schema.json").read_text())
ARGS = ["--board", "9x6", "--square", "25"]


@pytest.fixture(scope="module")
def frames():
    return [render_checkerboard(TRUE, board_view_pose(9, 6, SQUARE, distance_m=d, yaw_deg=y, pitch_deg=p,
                                                       roll_deg=r),
                                9, 6, SQUARE, supersample=8, blur_sigma_px=1.0, polarized=True,
                                sensor=SensorModel(), rng=k)
            for k, (y, p, r, d) in enumerate(VIEWS)]


@pytest.fixture(scope="module")
def raw_tiffs(frames, tmp_path_factory):
    d = tmp_path_factory.mktemp("raw")
    paths = []
    for k, f in enumerate(frames):
        paths.append(d / f"board_{k:02d}.tiff")
        tifffile.imwrite(paths[-1], f.raw)
    return paths


@pytest.fixture(scope="module")
def grey_pngs(frames, tmp_path_factory):
    """8-bit grey images of the noise-free S0, as an ordinary camera would give."""
    d = tmp_path_factory.mktemp("grey")
    paths = []
    for k, f in enumerate(frames):
        paths.append(d / f"grey_{k:02d}.png")
        cv2.imwrite(str(paths[-1]), np.clip(np.rint(f.s0 * 230.0), 0, 255).astype(np.uint8))
    return paths


def check_record(rec, *, k1_abs=0.03, c_px=3.0):
    jsonschema.validate(rec, SCHEMA, cls=jsonschema.Draft202012Validator)
    cam = CameraModel.from_dict(rec)
    assert (cam.width_px, cam.height_px, cam.pixel_size_um) == (816, 682, 3.45)
    assert cam.fx_px == pytest.approx(TRUE.fx_px, rel=5e-3) and cam.fy_px == pytest.approx(TRUE.fy_px, rel=5e-3)
    assert abs(cam.cx_px - TRUE.cx_px) < c_px and abs(cam.cy_px - TRUE.cy_px) < c_px
    assert abs(cam.distortion[0] - TRUE.distortion[0]) < k1_abs
    assert rec["rms_px"] < 0.4
    return cam


def test_dofp_frames_write_camera_json(raw_tiffs, tmp_path, capsys):
    out = tmp_path / "res" / "camera.json"
    assert main(["calibrate-camera", *map(str, raw_tiffs), *ARGS, "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and "Camera calibration: 12 of 12 views" in cap.err  # human messages on stderr
    assert cap.err.count("pihim: warning: narrow field of view") == 1
    rec = json.loads(out.read_text())
    check_record(rec)  # measured fx +0.000 %, cx +1.4 px, cy -0.2 px, k1 -0.018, RMS 0.026 px
    assert rec["rms_px"] < 0.06
    cal = rec["calibration"]
    assert cal["input"] == {"kind": "dofp", "demosaic": "full", "layout": "90,45,135,0",
                            "files": [str(p) for p in raw_tiffs]}
    assert cal["board"] == {"cols": 9, "rows": 6, "square_m": 0.025} and cal["image_binning"] == 1
    assert cal["views_used"] == 12 and cal["views_rejected"] == 0 and cal["flags"] == []
    assert [v["name"] for v in cal["views"]] == [str(p) for p in raw_tiffs]
    assert all(1.0 < v["distance_m"] < 1.3 and v["rms_px"] < 0.1 for v in cal["views"])
    assert rec["distortion_coefficients"] == [rec["distortion"][k] for k in ("k1", "k2", "p1", "p2", "k3")]
    assert [p.name for p in out.parent.iterdir()] == ["camera.json"]  # no temporary left over


def test_json_on_stdout_superpixel_and_fix_k3(raw_tiffs, tmp_path, capsys):
    out = tmp_path / "camera.json"
    argv = ["calibrate-camera", *map(str, raw_tiffs), *ARGS, "--out", str(out), "--json",
            "--demosaic", "superpixel", "--fix-k3", "--pixel-size-um", "3.45"]
    assert main(argv) == 0
    cap = capsys.readouterr()
    printed = json.loads(cap.out)
    assert printed == json.loads(out.read_text())
    assert "Camera calibration" in cap.err
    # half-resolution S0, corners mapped to sensor pixels: twice the corner noise (measured cy -2.9 px)
    cam = check_record(printed, c_px=6.0)
    assert cam.distortion[4] == 0.0 and printed["calibration"]["flags"] == ["CALIB_FIX_K3"]
    assert printed["calibration"]["image_binning"] == 2
    assert printed["calibration"]["input"]["demosaic"] == "superpixel"


def test_grey_images(grey_pngs, frames, tmp_path, capsys):
    out = tmp_path / "camera.json"
    assert main(["calibrate-camera", *map(str, grey_pngs), *ARGS, "--grey", "--fix-k3", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    check_record(rec, k1_abs=0.02)
    assert rec["calibration"]["input"] == {"kind": "grey", "demosaic": None, "layout": None,
                                           "files": [str(p) for p in grey_pngs]}
    # float32 S0 TIFFs at super-pixel resolution, as `pihim polar` writes them: --binning 2
    tiffs = []
    for k, f in enumerate(frames[:10]):
        tiffs.append(tmp_path / f"s0_{k}.S0.tiff")
        tifffile.imwrite(tiffs[-1], polar_image(f.raw).s0)
    out2 = tmp_path / "camera2.json"
    assert main(["calibrate-camera", *map(str, tiffs), *ARGS, "--grey", "--binning", "2", "--fix-k3",
                 "--out", str(out2)]) == 0
    rec2 = json.loads(out2.read_text())
    check_record(rec2, c_px=6.0)
    assert rec2["calibration"]["image_binning"] == 2 and rec2["calibration"]["views_used"] == 10
    capsys.readouterr()


def test_rejected_view_is_reported(raw_tiffs, tmp_path, capsys):
    blank = tmp_path / "blank.tiff"
    tifffile.imwrite(blank, np.full((682, 816), 1000, dtype=np.uint16))
    out = tmp_path / "camera.json"
    assert main(["calibrate-camera", *map(str, raw_tiffs[:5]), str(blank), *ARGS, "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert "blank image" in cap.err and "only 5 views used" in cap.err and cap.out == ""
    rec = json.loads(out.read_text())
    assert rec["calibration"]["views_rejected"] == 1 and rec["calibration"]["views"][5]["used"] is False
    assert rec["calibration"]["warnings"]


def _bad_cases(raw, tmp):
    blank = tmp / "blank.tiff"
    tifffile.imwrite(blank, np.zeros((682, 816), dtype=np.uint16))
    blank2 = tmp / "blank2.tiff"
    tifffile.imwrite(blank2, np.zeros((682, 816), dtype=np.uint16))
    small = tmp / "small.tiff"
    tifffile.imwrite(small, np.zeros((340, 408), dtype=np.uint16))
    grey = tmp / "grey.png"
    cv2.imwrite(str(grey), np.zeros((100, 120, 3), np.uint8))
    three = list(map(str, raw[:3]))
    link = tmp / "link.tiff"
    link.symlink_to(three[0])
    return {
        "missing file": ([str(tmp / "nope.tiff"), *three, *ARGS], "nope.tiff: no such file"),
        "bad board": ([*three, "--board", "9", "--square", "25"], "--board: expected inner corners"),
        "small board": ([*three, "--board", "2x6", "--square", "25"], "at least 3x3"),
        "square board": ([*three, "--board", "7x7", "--square", "25"], "is square"),
        "bad square": ([*three, "--board", "9x6", "--square", "-5"], "--square must be a positive number"),
        "no board": ([str(blank), str(blank2), *ARGS], "no image with a detectable 9x6 chessboard among 2"),
        "too few views": ([*three[:2], str(blank), *ARGS], "only 2 usable view(s)"),
        "sizes differ": ([*three, str(small), *ARGS], "images have different sizes"),
        "binning without grey": ([*three, *ARGS, "--binning", "2"], "--binning applies to --grey"),
        "huge binning": ([*three, *ARGS, "--grey", "--binning", "1000"], "--binning must be an integer from 1 to 16"),
        "a folder": ([str(tmp), *ARGS, "--grey"], "a folder; give the image files"),
        "colour grey image": ([str(grey), *ARGS, "--grey"], "expected a single-channel grey image"),
        "bad demosaic": ([*three, *ARGS, "--demosaic", "bilinear"], "--demosaic must be one of"),
        "out is a directory": ([*three, *ARGS], "is a directory"),
        # one view three times fitted k3 = +717 from "three views" (the same file, however spelt)
        "one view twice": ([*three, three[0], *ARGS], f"{three[0]}: given twice; give each view once"),
        "one view by two names": ([*three, str(link), *ARGS], f"{three[0]} and {link}: the same file"),
    }


@pytest.mark.parametrize("case", ["missing file", "bad board", "small board", "square board", "bad square",
                                  "no board", "too few views", "sizes differ", "binning without grey", "huge binning", "a folder",
                                  "colour grey image", "bad demosaic", "out is a directory", "one view twice",
                                  "one view by two names"])
def test_bad_input_is_one_line_exit_2_and_no_file(raw_tiffs, tmp_path, capsys, case):
    argv, message = _bad_cases(raw_tiffs, tmp_path)[case]
    out = tmp_path / "o" if case == "out is a directory" else tmp_path / "o" / "camera.json"
    if case == "out is a directory":
        out.mkdir()
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(["calibrate-camera", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pihim: error: ") and err.count("\n") == 1 and message in err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written, no temporary left
