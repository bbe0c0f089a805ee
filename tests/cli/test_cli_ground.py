"""End-to-end tests of ``pihim ground``."""

import json
from pathlib import Path

import numpy as np
import pytest

from pihim.cli import main


def test_ground_maps_written(tmp_path, capsys):
    out = tmp_path / "g"
    rc = main(["ground", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "5", "--out", str(out), "--json"])
    assert rc == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["schema"] == "pihim.ground/1"
    for key in ("ground_dolp_png", "ground_aop_png", "mirror_aop_png", "aop_difference_png", "npz"):
        assert (out / rec["files"][key].split("/")[-1]).stat().st_size > 0
    z = np.load(out / "ground-maps.npz")
    assert z["ground_aop_deg"].shape == (18, 72)
    d = z["aop_difference_deg"]
    ok = np.isfinite(d)
    assert ok.any() and (d[ok] >= 0).all() and (d[ok] <= 90).all()
    assert rec["fraction_usable"] == pytest.approx((d[ok] > 50).sum() / d.size)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--sun-zenith", "95", "--sun-azimuth", "0"], "zenith"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--model", "mie"], "sky model"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--sigma", "-2"], "sigma"),
        # the options named, not the library's parameters (sigma_deg, refractive_index, ...)
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--sigma", "1e9"], "--sigma must be a number of degrees in (0, 90]"),
        (["--sun-zenith", "30", "--sun-azimuth", "1e308"], "--sun-azimuth must be in [-360, 360] deg"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--mirror-normal-azimuth", "-1e300"],
         "--mirror-normal-azimuth must be in [-360, 360] deg"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--refractive-index", "0.5"], "--refractive-index must be"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--diffuse-albedo", "2"], "--diffuse-albedo must be in [0, 1]"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--sun-irradiance", "-1"], "--sun-irradiance must be"),
        (["--time", "2025-06-01T10:00"], "time"),
        (["--time", "yesterday-ish+01:00"], "time"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--mirror", "bronze"], "mirror"),
        # issue 10: validated before anything is computed or written (--seed -1 used to fail after four PNGs)
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--monte-carlo", "--seed", "-1"], "--seed"),
        # the Monte Carlo options without --monte-carlo were silently ignored
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--facets", "100"], "--facets set the monte carlo ground map"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--seed", "3"], "--seed set the monte carlo ground map: add --mon"),
        # requests too large for the machine are refused with the estimate (used to be MemoryError)
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--resolution", "0.001"], "needs about 32.4 tb of memory"),
        (["--sun-zenith", "30", "--sun-azimuth", "0", "--monte-carlo", "--facets", "1000000000000"],
         "needs about 730 tb of memory"),
    ],
)
def test_bad_input_one_line_exit_2(tmp_path, capsys, args, needle):
    out = tmp_path / "g"
    assert main(["ground", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err.lower()
    assert not out.exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs a /proc file system")
def test_out_that_cannot_be_created_is_one_line(capsys):
    rc = main(["ground", "--sun-zenith", "30", "--sun-azimuth", "0", "--resolution", "10", "--out", "/proc/x"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("pihim: error: --out /proc/x: cannot create")


def test_success_says_what_was_written(tmp_path, capsys):
    out = tmp_path / "g"
    assert main(["ground", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "5", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert cap.out == "" and len(lines) == 2
    assert lines[0].startswith("pihim ground: sun zenith 30.0 deg, azimuth 235.0 deg; the mirror shows ground in")
    assert "ground-vs-ground usable in" in lines[0]
    assert lines[1].startswith(f"wrote 5 files to {out}: ground-dolp.png") and lines[1].endswith("ground-maps.npz")


def test_defaults_are_the_conventions(tmp_path, capsys):
    """Pinned conventions: without options, the ground has n = 1.45 (paper), the mirror is second-surface silvered
    glass and the Monte Carlo uses the paper's 100,000 microfacets; the maps equal those asked for explicitly."""
    sun = ["--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "10"]

    def run(name, *extra):
        assert main(["ground", *sun, *extra, "--out", str(tmp_path / name), "--json"]) == 0
        return json.loads(capsys.readouterr().out), np.load(tmp_path / name / "ground-maps.npz")

    rec, default = run("default", "--monte-carlo")
    assert rec["ground"]["refractive_index"] == 1.45
    assert rec["mirror"]["model"] == "second-surface"
    assert rec["monte_carlo"]["facets"] == 100_000
    _, explicit = run("explicit", "--refractive-index", "1.45", "--mirror", "second-surface")
    _, fresnel = run("fresnel", "--mirror", "fresnel")
    _, glass = run("glass", "--refractive-index", "1.54")
    for key in ("ground_dolp", "ground_aop_deg", "mirror_dolp", "mirror_aop_deg"):
        assert np.array_equal(default[key], explicit[key], equal_nan=True), key
    assert not np.allclose(default["mirror_dolp"], fresnel["mirror_dolp"], equal_nan=True)
    assert not np.allclose(default["ground_dolp"], glass["ground_dolp"], equal_nan=True)


def test_json_names_the_mirror_model_and_folds_its_azimuth(tmp_path, capsys):
    """--mirror is matched case-insensitively: the record gives the model's name, and the azimuth in [0, 360)."""
    assert main(["ground", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "10", "--mirror", " Ideal",
                 "--mirror-normal-azimuth", "-90", "--out", str(tmp_path / "g"), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["mirror"]["model"] == "ideal" and rec["mirror"]["normal_azimuth_deg"] == 270.0
