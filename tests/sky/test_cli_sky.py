"""End-to-end tests of ``pihim sky``: files, JSON, one-line errors with exit 2, no partial output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pihim.cli import app, main
from pihim.cli.sky import sky
from pihim.sky.sun import NSTTF, sun_position

# The lead registers the command in pihim.cli; until then, register it here.
if not any((c.name or getattr(c.callback, "__name__", "")) == "sky" for c in app.registered_commands):
    app.command("sky")(sky)


def _json(capsys):
    out = capsys.readouterr()
    lines = [ln for ln in out.out.splitlines() if ln.strip()]
    assert len(lines) == 1
    return json.loads(lines[0]), out.err


def test_sun_angles_rayleigh_writes_maps_and_json(tmp_path, capsys):
    out = tmp_path / "sky"
    rc = main(["sky", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "1", "--out", str(out), "--json"])
    assert rc == 0
    rec, err = _json(capsys)
    assert err == ""
    assert sorted(p.name for p in out.iterdir()) == ["sky-aop.png", "sky-dolp.png", "sky-maps.npz"]
    for name in ("sky-aop.png", "sky-dolp.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with np.load(out / "sky-maps.npz") as z:
        assert z["dolp"].shape == z["aop_deg"].shape == z["s0"].shape == z["zenith_deg"].shape == (90, 360)
        assert z["azimuth_deg"][0, :3].tolist() == [0.5, 1.5, 2.5]
        assert float(z["sun_azimuth_deg"]) == 235.0
        assert "local meridian" in str(z["aop_reference"])
        assert np.nanmax(z["dolp"]) == pytest.approx(0.8, abs=1e-3)
    assert rec["sun"]["zenith_deg"] == 30.0 and rec["sun"]["azimuth_deg"] == 235.0
    assert rec["model"]["kind"] == "rayleigh" and rec["grid_shape"] == [90, 360]
    assert rec["dolp_max"]["value"] == pytest.approx(0.8, abs=1e-3)
    assert rec["dolp_max"]["scattering_angle_deg"] == pytest.approx(90.0, abs=1.0)
    assert rec["band_90deg_from_sun"]["dolp_mean"] == pytest.approx(0.8, abs=2e-3)
    assert rec["files"]["npz"].endswith("sky-maps.npz")


def test_time_and_site_berry(tmp_path, capsys):
    out = tmp_path / "b"
    t = "2024-06-21T10:00:00-06:00"
    args = ["sky", "--time", t, "--site", "nsttf", "--model", "berry", "--neutral-separation", "20",
            "--dmax", "0.7", "--resolution", "2", "--out", str(out), "--json"]
    assert main(args) == 0
    rec, _ = _json(capsys)
    ref = sun_position(NSTTF, t)
    assert rec["sun"]["zenith_deg"] == pytest.approx(ref.zenith_deg)
    assert rec["sun"]["azimuth_deg"] == pytest.approx(ref.azimuth_deg)
    assert rec["site"]["name"] == "NSTTF" and rec["time"] == "2024-06-21T10:00:00-06:00"
    assert rec["model"] == {"kind": "berry", "dmax": 0.7, "radiance": "cie-clear",
                            "neutral_point_separation_deg": 20.0, "scale": 1.0}
    # Berry lowers DoLP on the 90-deg band where it crosses the sun's vertical
    assert rec["band_90deg_from_sun"]["dolp_min"] < 0.65 < rec["band_90deg_from_sun"]["dolp_max"]


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--time", "2024-06-21T10:00:00"], "no UTC offset"),
        (["--time", "tomorrow"], "ISO 8601"),
        (["--time", "2024-06-21T23:30:00-06:00"], "below the horizon"),
        (["--sun-zenith", "95", "--sun-azimuth", "10"], "sun-zenith"),
        (["--sun-zenith", "-1", "--sun-azimuth", "10"], "sun-zenith"),
        (["--sun-zenith", "30"], "sun-azimuth"),
        (["--sun-zenith", "30", "--sun-azimuth", "10", "--model", "mie"], "unknown sky model"),
        (["--sun-zenith", "30", "--sun-azimuth", "10", "--dmax", "1.5"], "dmax"),
        (["--sun-zenith", "30", "--sun-azimuth", "10", "--resolution", "0.7"], "resolution"),
        (["--sun-zenith", "30", "--sun-azimuth", "10", "--time", "2024-06-21T10:00:00-06:00"], "not both"),
        (["--sun-zenith", "30", "--sun-azimuth", "10", "--site", "nsttf"], "--site needs --time"),
        (["--time", "2024-06-21T10:00:00-06:00", "--site", "95,0,0"], "latitude"),
        (["--sun-zenith", "abc", "--sun-azimuth", "10"], "sun-zenith"),
        # issue 10: out-of-range numbers
        (["--time", "2024-06-21T10:00:00-06:00", "--site", "0,0,1e300"], "site height"),
        (["--time", "9999-06-21T10:00:00-06:00"], "outside the years"),
        # an option the model does not use is refused, not silently ignored
        (["--sun-zenith", "30", "--sun-azimuth", "10", "--neutral-separation", "20"],
         "--neutral-separation applies to --model berry"),
    ],
)
def test_bad_input_exits_2_with_one_line_and_no_files(tmp_path, capsys, args, needle):
    out = tmp_path / "never"
    assert main(["sky", *args, "--out", str(out), "--json"]) == 2
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pihim: error:") and needle in lines[0]
    assert "Traceback" not in cap.err and cap.out == ""
    assert not out.exists()


def test_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["sky", "--sun-zenith", "30", "--sun-azimuth", "10", "--out", str(f)]) == 2
    assert "not a directory" in capsys.readouterr().err


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs a /proc file system")
def test_out_that_cannot_be_created_is_one_line(tmp_path, capsys):
    # issue 10: 'pihim sky --out /proc/x' was a FileNotFoundError traceback
    rc = main(["sky", "--sun-zenith", "30", "--sun-azimuth", "10", "--resolution", "5", "--out", "/proc/x"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("pihim: error: --out /proc/x: cannot create")


def test_resolution_too_fine_for_memory_refused_with_the_figure(tmp_path, capsys, monkeypatch):
    import pihim._resources as resources

    monkeypatch.setattr(resources, "available_memory", lambda: 10_000_000)  # 10 MB left
    rc = main(["sky", "--sun-zenith", "30", "--sun-azimuth", "10", "--resolution", "0.5", "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err.strip().splitlines()
    # 180 x 720 directions x 280 B = 36.3 MB
    assert rc == 2 and len(err) == 1 and "needs about 36.3 MB of memory; 10 MB is available" in err[0]
    assert not (tmp_path / "s").exists()


def test_success_says_what_was_written(tmp_path, capsys):
    out = tmp_path / "sky"
    assert main(["sky", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "2", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert cap.out == "" and len(lines) == 2
    assert lines[0].startswith("pihim sky: sun zenith 30.0 deg, azimuth 235.0 deg, rayleigh; DoLP max 0.80")
    assert "(90 deg from the sun)" in lines[0]
    assert lines[1] == f"wrote 3 files to {out}: sky-dolp.png, sky-aop.png, sky-maps.npz"
