"""End-to-end tests of ``pihim polar`` and the atomic-output guarantee."""

import json
from importlib import resources

import jsonschema
import numpy as np
import pytest
import tifffile

from pihim._atomic import atomic_path
from pihim.cli import main
from pihim.polarimetry import aop_difference_deg, stokes_from_dolp_aop
from pihim.render import mosaic_from_stokes

SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/polar-frame.schema.json").read_text())


@pytest.fixture
def frame(tmp_path):
    s = stokes_from_dolp_aop(np.full((32, 40), 2400.0), 0.35, 123.0)
    path = tmp_path / "in" / "frame_a.tiff"
    path.parent.mkdir()
    tifffile.imwrite(path, mosaic_from_stokes(*s, bit_depth=12))
    return path


def _records(capsys):
    out = capsys.readouterr()
    recs = [json.loads(line) for line in out.out.splitlines() if line.strip()]
    for r in recs:
        jsonschema.validate(r, SCHEMA)
    return recs, out.err


def test_polar_writes_float32_tiffs_and_json(frame, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["polar", str(frame), "--out", str(out), "--json", "--png"]) == 0
    recs, err = _records(capsys)
    assert len(recs) == 1 and recs[0]["status"] == "ok" and err == ""
    dolp = tifffile.imread(out / "frame_a.DoLP.tiff")
    aop = tifffile.imread(out / "frame_a.AoP.tiff")
    s0 = tifffile.imread(out / "frame_a.S0.tiff")
    assert dolp.dtype == aop.dtype == s0.dtype == np.float32
    assert dolp.shape == (16, 20)
    assert np.allclose(dolp, 0.35, atol=2e-3)
    assert np.max(aop_difference_deg(aop, 123.0)) < 0.2
    assert np.allclose(s0, 2400.0, rtol=2e-3)
    for name in ("S0", "DoLP", "AoP"):
        assert (out / f"frame_a.{name}.png").stat().st_size > 0
    assert recs[0]["dolp"]["median"] == pytest.approx(0.35, abs=2e-3)


def test_batch_continues_after_bad_items(frame, tmp_path, capsys):
    bad_odd = tmp_path / "in" / "odd.tiff"
    tifffile.imwrite(bad_odd, np.zeros((5, 6), np.uint16))
    corrupt = tmp_path / "in" / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    missing = tmp_path / "in" / "missing.tiff"
    out = tmp_path / "out"
    rc = main(["polar", str(bad_odd), str(corrupt), str(missing), str(frame), "--out", str(out), "--json"])
    assert rc == 2
    recs, err = _records(capsys)
    assert [r["status"] for r in recs] == ["error", "error", "error", "ok"]
    lines = [ln for ln in err.splitlines() if ln.startswith("pihim: error:")]
    assert len(lines) == 3
    assert "odd.tiff" in lines[0] and "corrupt.png" in lines[1] and "missing.tiff" in lines[2]
    assert "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["frame_a.AoP.tiff", "frame_a.DoLP.tiff", "frame_a.S0.tiff"]


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--layout", "0,45,90"], "layout"),
        (["--demosaic", "nearest"], "demosaic"),
        (["--calibration", "nope.json"], "calibration"),
        (["--bogus-option"], "bogus"),
        (["--dark-level", "-10"], "--dark-level must be a finite number of raw units >= 0, got -10"),
    ],
)
def test_bad_options_one_line_exit_2(frame, tmp_path, capsys, extra, needle):
    rc = main(["polar", str(frame), "--out", str(tmp_path / "o"), *extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and needle in err.lower()
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_colliding_stems_refused(frame, tmp_path, capsys):
    other = tmp_path / "frame_a.tiff"
    other.write_bytes(frame.read_bytes())
    assert main(["polar", str(frame), str(other), "--out", str(tmp_path / "o")]) == 2
    assert "collide" in capsys.readouterr().err


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "x.tiff"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("killed mid-write")
    assert list(tmp_path.iterdir()) == []
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole" and [p.name for p in tmp_path.iterdir()] == ["x.tiff"]


def test_calibration_changes_result(frame, tmp_path, capsys):
    from pihim.polarimetry import AnalyserMatrix

    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(AnalyserMatrix.from_parameters([0, 45, 90, 135], [1.0, 1.2, 1.0, 1.0]).to_dict()))
    assert main(["polar", str(frame), "--out", str(tmp_path / "o"), "--calibration", str(cal), "--json"]) == 0
    recs, _ = _records(capsys)
    assert recs[0]["calibrated"] is True
    # a 20% gain on the 45 deg channel that the frame does not have biases the result
    assert abs(recs[0]["dolp"]["median"] - 0.35) > 0.02


def test_success_is_reported_and_png_adds_a_captioned_figure(frame, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["polar", str(frame), "--out", str(out), "--png"]) == 0
    cap = capsys.readouterr()
    assert cap.out == ""
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"pihim polar: 1 of 1 frames -> {out}")
    assert "median DoLP 0.350-0.350" in err[0] and "polar.png" in err[0]
    fig = out / "frame_a.polar.png"
    data = fig.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000  # three panels, colour bars and the AoP key


def test_a_directory_is_reported_as_a_directory(frame, tmp_path, capsys):
    folder = tmp_path / "frames"  # no extension: used to be "unsupported file type '(no extension)'"
    folder.mkdir()
    assert main(["polar", str(folder), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "is a directory" in err and "unsupported" not in err
