"""End-to-end tests of ``pihim calibrate-polarizer``."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import tifffile

from pihim.camera import IMX250MZR, MosaicLayout
from pihim.cli import main
from pihim.polarimetry import AnalyserMatrix, aop_difference_deg, stokes_from_dolp_aop
from pihim.render import mosaic_from_stokes

TRUE = AnalyserMatrix.from_parameters(
    [1.5, 46.2, 88.8, 136.7], [1.0, 0.93, 1.06, 0.97], [120.0, 80.0, 300.0, 150.0]
)
ANGLES = np.arange(0.0, 180.0, 22.5)
DARK = 64


def render(angles, *, layout=IMX250MZR, polarizer_dolp=1.0, shape=(96, 128), seed=0):
    """Noisy 12-bit frames of a uniformly lit scene behind a polarizer at each angle."""
    rng = np.random.default_rng(seed)
    return [
        mosaic_from_stokes(
            *stokes_from_dolp_aop(np.full(shape, 3000.0), polarizer_dolp, a),
            layout=layout,
            analyser=TRUE,
            dark_level=DARK,
            read_noise_dn=2.5,
            electrons_per_dn=2.0,
            rng=rng,
        )
        for a in angles
    ]


def write_tiffs(directory, frames, shift=0):
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for j, f in enumerate(frames):
        p = directory / f"pol_{j:02d}.tiff"
        tifffile.imwrite(p, (f.astype(np.uint16) << shift))
        paths.append(p)
    return paths


def check_matrix(matrix, *, t_rel=5e-3, ang_deg=0.1, d_abs=3e-3):
    a = AnalyserMatrix(np.asarray(matrix))
    t_true = TRUE.transmission / TRUE.transmission.mean()
    assert np.max(np.abs(a.transmission / t_true - 1)) < t_rel
    assert np.max(aop_difference_deg(a.angles_deg, TRUE.angles_deg)) < ang_deg
    assert np.max(np.abs(a.diattenuation - TRUE.diattenuation)) < d_abs


@pytest.fixture(scope="module")
def tiffs(tmp_path_factory):
    return write_tiffs(tmp_path_factory.mktemp("frames"), render(ANGLES))


def test_writes_calibration_json(tiffs, tmp_path, capsys):
    out = tmp_path / "res" / "calib.json"
    argv = ["calibrate-polarizer", *map(str, tiffs), "--angles", "0:180:22.5", "--out", str(out)]
    assert main([*argv, "--dark-level", str(DARK)]) == 0
    cap = capsys.readouterr()
    assert "Polarizer calibration" in cap.err and cap.out == ""  # human output goes to stderr (docs/cli.md)
    rec = json.loads(out.read_text())
    assert rec["schema"] == "pihim.analyser/1"
    check_matrix(rec["matrix"])
    cal = rec["calibration"]
    assert cal["n_frames"] == 8 and cal["polarizer_angles_deg"] == ANGLES.tolist()
    assert cal["frames"] == [str(p) for p in tiffs]
    assert cal["dark_level"] == DARK and cal["bit_depth"] == 12 and cal["msb_shift"] == 0
    assert cal["layout"] == "90,45,135,0" and cal["polarizer_dolp"] == 1.0
    assert cal["roi"] == {"x": 32, "y": 24, "width": 64, "height": 48}
    assert max(cal["residual_rms_relative"]) < 3e-3 and cal["warnings"] == []
    loaded = AnalyserMatrix.load(out)  # what `pihim polar --calibration` reads
    assert np.array_equal(loaded.matrix, np.array(rec["matrix"]))
    assert [p.name for p in out.parent.iterdir()] == ["calib.json"]  # no temporary left over


def test_json_on_stdout_and_summary_on_stderr(tiffs, tmp_path, capsys):
    out = tmp_path / "calib.json"
    angles = ",".join(f"{a:g}" for a in ANGLES)
    argv = ["calibrate-polarizer", *map(str, tiffs), "--angles", angles, "--out", str(out), "--json"]
    assert main([*argv, "--dark-level", "64", "--fit-drift"]) == 0
    cap = capsys.readouterr()
    printed = json.loads(cap.out)
    assert printed == json.loads(out.read_text())
    assert "Polarizer calibration" in cap.err
    assert printed["calibration"]["fit_frame_scale"] is True
    assert np.allclose(printed["calibration"]["frame_scale"], 1.0, atol=3e-3)
    check_matrix(printed["matrix"])


def test_layout_roi_bitdepth_and_polarizer_dolp(tmp_path, capsys):
    layout = MosaicLayout(((0, 45), (135, 90)))
    angles = np.arange(0.0, 180.0, 30.0)
    paths = write_tiffs(tmp_path / "f", render(angles, layout=layout, polarizer_dolp=0.9), shift=4)
    out = tmp_path / "c.json"
    argv = ["calibrate-polarizer", *map(str, paths), "--angles", "0:180:30", "--out", str(out)]
    opts = ["--layout", "0,45,135,90", "--roi", "9,7,101,80", "--bit-depth", "12", "--polarizer-dolp", "0.9"]
    assert main([*argv, *opts, "--dark-level", "64"]) == 0
    rec = json.loads(out.read_text())
    check_matrix(rec["matrix"])
    cal = rec["calibration"]
    assert cal["roi"] == {"x": 10, "y": 8, "width": 100, "height": 78}
    assert cal["bit_depth"] == 12 and cal["msb_shift"] == 4 and cal["layout"] == "0,45,135,90"
    assert cal["polarizer_dolp"] == 0.9
    # the same frames with the default layout: channels land on the wrong angles, and it is flagged
    assert main([*argv, "--dark-level", "64", "--polarizer-dolp", "0.9"]) == 0
    assert "off nominal" in capsys.readouterr().err
    wrong = AnalyserMatrix.load(out)
    assert np.max(aop_difference_deg(wrong.angles_deg, TRUE.angles_deg)) > 40


def test_lucid_raw_buffers(tmp_path, capsys):
    frames = render(ANGLES[::2], shape=(32, 48))
    paths = []
    for j, f in enumerate(frames):
        p = tmp_path / f"buf{j}.raw"
        p.write_bytes(f.astype("<u2").tobytes())
        paths.append(p)
    out = tmp_path / "c.json"
    argv = ["calibrate-polarizer", *map(str, paths), "--angles", "0,45,90,135", "--out", str(out)]
    fmt = ["--width", "48", "--height", "32", "--pixel-format", "PolarizeMono16", "--dark-level", "64"]
    assert main([*argv, *fmt, "--bit-depth", "12"]) == 0
    check_matrix(json.loads(out.read_text())["matrix"], t_rel=1e-2, ang_deg=0.3, d_abs=5e-3)


def _bad_cases(tiffs, tmp):
    corrupt = tmp / "corrupt.tiff"
    corrupt.write_bytes(b"II*\x00garbage")
    frames = [str(p) for p in tiffs]
    ok = "0:180:22.5"
    fifo = tmp / "fifo.raw"
    if not fifo.exists():
        os.mkfifo(fifo)
    return {
        "missing frame": ([*frames[:-1], str(tmp / "nope.tiff")], ["--angles", ok]),
        "corrupt frame": ([*frames[:-1], str(corrupt)], ["--angles", ok]),
        "bad angles": (frames, ["--angles", "0,22.5,abc,67.5,90,112.5,135,157.5"]),
        "bad angle range": (frames, ["--angles", "0:180"]),
        "count mismatch": (frames, ["--angles", "0,45,90,135"]),
        "unknown layout": (frames, ["--angles", ok, "--layout", "imx999"]),
        "too few distinct": (frames, ["--angles", "0,0,45,45,90,90,180,180"]),
        "bad roi": (frames, ["--angles", ok, "--roi", "1,2,3"]),
        "roi outside": (frames, ["--angles", ok, "--roi", "100,0,64,64"]),
        "bad dolp": (frames, ["--angles", ok, "--polarizer-dolp", "1.5"]),
        "bad bit depth": (frames, ["--angles", ok, "--bit-depth", "10"]),
        "raw without size": ([str(tmp / "x.raw")] * 8, ["--angles", ok]),
        "drift with 4 angles": (frames[:4], ["--angles", "0,45,90,135", "--fit-drift"]),
        "missing --angles": (frames, []),
        # issue 10: a range of 1e18 angles grew to 3.9 GB; a FIFO blocked forever
        "huge angle range": (frames, ["--angles", "0:1e9:1e-9"]),
        "fifo frame": ([*frames[:-1], str(fifo)], ["--angles", ok, "--width", "128", "--height", "96"]),
        "nan dark level": (frames, ["--angles", ok, "--dark-level", "nan"]),
    }


@pytest.mark.parametrize(
    "case",
    [
        "missing frame",
        "corrupt frame",
        "bad angles",
        "bad angle range",
        "count mismatch",
        "unknown layout",
        "too few distinct",
        "bad roi",
        "roi outside",
        "bad dolp",
        "bad bit depth",
        "raw without size",
        "drift with 4 angles",
        "missing --angles",
        "huge angle range",
        "fifo frame",
        "nan dark level",
    ],
)
def test_bad_input_exits_2_with_one_line_and_no_output(case, tiffs, tmp_path, capsys):
    frames, opts = _bad_cases(tiffs, tmp_path)[case]
    out = tmp_path / "res" / "calib.json"
    assert main(["calibrate-polarizer", *frames, *opts, "--out", str(out)]) == 2
    cap = capsys.readouterr()
    lines = cap.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("pihim: error: "), cap.err
    assert cap.out == ""
    assert not out.parent.exists()


def test_failed_run_keeps_previous_calibration(tiffs, tmp_path, capsys):
    out = tmp_path / "calib.json"
    out.write_text('{"matrix": "previous"}')
    assert main(["calibrate-polarizer", *map(str, tiffs), "--angles", "0,45", "--out", str(out)]) == 2
    assert out.read_text() == '{"matrix": "previous"}'
    assert [p.name for p in tmp_path.iterdir()] == ["calib.json"]


def test_unwritable_output_is_an_input_error(tiffs, tmp_path, capsys):
    target = tmp_path / "adir"
    target.mkdir()
    (target / "keep").write_text("x")
    assert main(["calibrate-polarizer", *map(str, tiffs), "--angles", "0:180:22.5", "--out", str(target)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "cannot write the calibration" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]
    assert [p.name for p in target.iterdir()] == ["keep"]
