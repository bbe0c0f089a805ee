"""End-to-end tests of ``pihim simulate`` (small frames, the Triton's field of view)."""

import json
from importlib import resources

import jsonschema
import numpy as np
import pytest
import tifffile

from pihim.cli import main
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.render.paths import MIRROR
from pihim.sky.sun import NSTTF, parse_time, sun_position

SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/simulated-frame.schema.json").read_text())
TIME = "2021-05-13T13:00-06:00"
FILES = ["FRAME.tiff", "FRAME.json", "FRAME.S0.tiff", "FRAME.DoLP.tiff", "FRAME.AoP.tiff", "FRAME.labels.tiff"]


@pytest.fixture(scope="module")
def geometry():
    """Mirror centre, frame and pivot of 8E3 as tracked at TIME."""
    field = nsttf_like_field()
    pose = track_field(field, sun_position(NSTTF, parse_time(TIME)).vector, UFACET_AIM_POINT)
    i = field.index("8E3")
    return pose.mirror_centres[i], pose.rotations[i], field


def _xyz(p):
    return ",".join(f"{v:.6f}" for v in p)


def test_pair_frame_written_with_log_truth_and_schema(tmp_path, capsys):
    out = tmp_path / "sim" / "FRAME.tiff"
    rc = main(["simulate", "--time", TIME, "--hua", "8E3", "--target", "7E3", "--size", "160x128",
               "--supersample", "1", "--canting-sigma-mrad", "1", "--tracking-sigma-mrad", "0.5",
               "--gps-sigma-m", "0.3", "--attitude-sigma-deg", "0.2", "--seed", "9", "--json", "--out", str(out)])
    assert rc == 0
    cap = capsys.readouterr()
    lines = cap.out.strip().splitlines()
    assert len(lines) == 1
    summary = json.loads(lines[0])
    assert summary["schema"] == "pihim.simulate-summary/1"
    assert summary["hua"] == "8E3" and summary["target"] == "7E3" and summary["rays"] >= 160 * 128
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(FILES)
    assert summary["files"]["raw"] == str(out)
    doc = json.loads((out.parent / "FRAME.json").read_text())
    jsonschema.validate(doc, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert doc["log"]["field"] == {"source": "nsttf-like", "facets": None, "heliostat_count": 218}
    assert doc["log"]["camera"]["width_px"] == 160
    assert doc["truth"]["simulation"]["seed"] == 9
    raw = tifffile.imread(out)
    labels = tifffile.imread(out.parent / "FRAME.labels.tiff")
    assert raw.dtype == np.uint16 and raw.shape == (128, 160) and labels.shape == (128, 160, 7)
    names = doc["truth"]["labels"]["heliostat_index"]
    hua = (labels[..., 0] == MIRROR) & (labels[..., 1] == names.index("8E3"))
    assert (hua & (labels[..., 4] == names.index("7E3"))).sum() > 0.2 * hua.sum() > 0
    # the next step of a real campaign reads the raw frame
    assert main(["polar", str(out), "--out", str(tmp_path / "polar")]) == 0


def test_human_summary_on_stderr(tmp_path, capsys, geometry):
    centre = geometry[0]
    out = tmp_path / "f.tif"
    rc = main(["simulate", "--time", TIME, "--camera", "24,75,20", "--look-at", _xyz(centre), "--roll", "5",
               "--size", "64x48", "--supersample", "1", "--out", str(out)])
    assert rc == 0
    cap = capsys.readouterr()
    assert cap.out == ""
    err = cap.err.strip().splitlines()
    assert 1 <= len(err) <= 2 and "wrote" in err[0] and "rays" in err[-1]
    assert (tmp_path / "f.json").is_file() and (tmp_path / "f.labels.tif").is_file()
    assert json.loads((tmp_path / "f.json").read_text())["truth"]["pose"]["roll_deg"] == pytest.approx(5.0)


def test_same_seed_same_bytes_other_seed_other_raw(tmp_path, geometry):
    centre = geometry[0]
    args = ["simulate", "--time", TIME, "--camera", "24,75,20", "--look-at", _xyz(centre), "--size", "64x48",
            "--supersample", "1", "--canting-sigma-mrad", "2", "--gps-sigma-m", "1", "--attitude-sigma-deg", "1"]
    for d, seed in (("a", "1"), ("b", "1"), ("c", "2")):
        assert main([*args, "--seed", seed, "--out", str(tmp_path / d / "FRAME.tiff")]) == 0
    for name in FILES:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert (tmp_path / "a" / "FRAME.tiff").read_bytes() != (tmp_path / "c" / "FRAME.tiff").read_bytes()
    assert (tmp_path / "a" / "FRAME.json").read_bytes() != (tmp_path / "c" / "FRAME.json").read_bytes()


def _bad_cases(geometry):
    centre, rot, field = geometry
    pivot = field.pivot("8E3")
    look = ["--look-at", _xyz(centre)]
    return {
        "camera below the ground": (["--camera", "24,75,-2", *look], "below the ground"),
        "camera inside a heliostat": (["--camera", _xyz(centre + 0.2 * rot[:, 2]), "--look-at", "0,0,0"],
                                      "inside heliostat 8e3"),
        "camera in the mirror box": (["--camera", _xyz(centre + 2.5 * rot[:, 0] + 0.05 * rot[:, 2]),
                                      "--look-at", "0,0,0"], "inside heliostat 8e3"),
        "camera in the pedestal": (["--camera", _xyz(pivot - [0, 0, 1.0]), *look], "inside heliostat 8e3"),
        "unknown heliostat": (["--hua", "8E3", "--target", "99W1"], "unknown heliostat"),
        "look-at equal to position": (["--camera", "24,75,20", "--look-at", "24,75,20"], "equals --camera"),
        "night": (["--camera", "24,75,20", *look, "--time", "2021-05-13T02:00-06:00"], "below the horizon"),
        "negative sigma": (["--camera", "24,75,20", *look, "--canting-sigma-mrad", "-1"], "canting sigma"),
        "negative gps sigma": (["--camera", "24,75,20", *look, "--gps-sigma-m", "-0.5"], "gps sigma"),
        "negative seed": (["--camera", "24,75,20", *look, "--seed", "-3"], "seed"),
        "two pose groups": (["--camera", "24,75,20", *look, "--hua", "8E3", "--target", "7E3"], "exactly one"),
        "no pose": ([], "exactly one"),
        "hua without target": (["--hua", "8E3"], "go together"),
        "roll alone": (["--roll", "3", "--hua", "8E3", "--target", "7E3"], "exactly one"),
        "huge roll": (["--camera", "24,75,20", *look, "--roll", "1e308"], "--roll must be in [-360, 360] deg"),
        "target not visible": (["--hua", "8E3", "--target", "14W6"], "not visible in hua 8e3"),
        "bad waypoint": (["--waypoint", "plan.json"], "plan.json:index"),
        "missing plan": (["--waypoint", "nowhere/plan.json:0"], "no such file"),
        "odd size": (["--camera", "24,75,20", *look, "--size", "65x48"], "even"),
        "bad supersample": (["--camera", "24,75,20", *look, "--supersample", "0"], "supersample"),
        "naive time": (["--camera", "24,75,20", *look, "--time", "2021-05-13T13:00"], "utc offset"),
        # issue 10: sizes the machine cannot hold are refused before rendering
        "huge size": (["--camera", "24,75,20", *look, "--size", "100000x100000"], "needs about 1.5 tb of memory"),
    }


@pytest.mark.parametrize("case", [
    "camera below the ground", "camera inside a heliostat", "camera in the mirror box", "camera in the pedestal",
    "unknown heliostat", "look-at equal to position", "night", "negative sigma", "negative gps sigma",
    "negative seed", "two pose groups", "no pose", "hua without target", "roll alone", "huge roll", "target not visible",
    "bad waypoint", "missing plan", "odd size", "bad supersample", "naive time", "huge size",
])
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, geometry, case):
    args, needle = _bad_cases(geometry)[case]
    if "--time" not in args:
        args = [*args, "--time", TIME]
    out_dir = tmp_path / "o"
    out_dir.mkdir()
    argv = ["simulate", *args]
    if "--size" not in args:
        argv += ["--size", "64x48"]
    if "--supersample" not in args:
        argv += ["--supersample", "1"]
    rc = main([*argv, "--out", str(out_dir / "FRAME.tiff")])
    assert rc == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("pihim: error:"), err
    assert needle in err.lower(), err
    assert list(out_dir.iterdir()) == []
    assert cap.out == ""


@pytest.mark.parametrize("out_name, needle", [("FRAME.png", ".tiff"), ("", "directory")])
def test_bad_output_name(tmp_path, capsys, out_name, needle):
    out = tmp_path / out_name if out_name else tmp_path / "d.tiff"
    if not out_name:
        out.mkdir()
    rc = main(["simulate", "--time", TIME, "--hua", "8E3", "--target", "7E3", "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err
    assert not out.exists() or out.is_dir() and list(out.iterdir()) == []


@pytest.mark.parametrize("beside", ["d.json", "d.S0.tiff"])
def test_a_directory_where_a_file_beside_the_frame_goes(tmp_path, capsys, beside):
    """``d.json`` a directory: one line naming it, exit 2, before rendering (it was exit 1 naming d.tiff)."""
    (tmp_path / beside).mkdir()
    rc = main(["simulate", "--time", TIME, "--hua", "8E3", "--target", "7E3", "--out", str(tmp_path / "d.tiff")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and f"{tmp_path / beside}, one of the files written" in err
    assert sorted(q.name for q in tmp_path.iterdir()) == [beside]


def test_deeply_nested_waypoint_plan_is_one_line(tmp_path, capsys):
    plan = tmp_path / "plan.json"
    plan.write_text("[" * 100_000 + "]" * 100_000)
    out = tmp_path / "o" / "FRAME.tiff"
    assert main(["simulate", "--time", TIME, "--waypoint", f"{plan}:0", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nested too deeply" in err[0] and not out.parent.exists()


def test_supersample_default_is_the_renderer_default():
    """``pihim simulate`` states the renderer's default without importing the renderer (start-up)."""
    from pihim.cli.simulate import DEFAULT_SUPERSAMPLE
    from pihim.render.frame import RenderSettings

    assert DEFAULT_SUPERSAMPLE == RenderSettings().supersample


def _one_waypoint_plan(tmp_path, site=(34.962276, -106.509606)):
    """A plan.json of one capture waypoint (x, y, z = 24, 75, 20 m, looking North and down) made at TIME."""
    wp = {"x_m": 24.0, "y_m": 75.0, "z_m": 20.0, "heading_deg": 0.0, "gimbal_pitch_deg": -45.0, "capture": True,
          "hua": "8E3"}
    plan = {"schema": "pihim.plan/1", "time_iso": TIME, "site": {"latitude_deg": site[0], "longitude_deg": site[1]},
            "passes": [{"waypoints": [wp], "predictions": [{"hua": "8E3", "target": "7E3", "waypoint_index": 0}]}]}
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(plan))
    return path


def test_a_waypoint_renders_at_the_plans_time_unless_told(tmp_path, capsys):
    """--time was required with --waypoint, and a time other than the plan's went unsaid."""
    plan = _one_waypoint_plan(tmp_path)
    out = tmp_path / "a.tiff"
    assert main(["simulate", "--waypoint", f"{plan}:0", "--size", "16x16", "--out", str(out), "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["time"] == "2021-05-13T13:00:00-06:00" and "note" not in cap.err
    assert main(["simulate", "--waypoint", f"{plan}:0", "--time", "2021-05-13T14:00-06:00", "--size", "16x16",
                 "--out", str(tmp_path / "b.tiff"), "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["time"] == "2021-05-13T14:00:00-06:00"
    assert cap.err.strip() == ("pihim simulate: note: --time 2021-05-13T14:00-06:00 is not the time the plan was "
                               "made for (2021-05-13T13:00-06:00); the field tracks the sun of --time")
    assert main(["simulate", "--hua", "8E3", "--target", "7E3", "--size", "16x16", "--out", str(out)]) == 2
    assert "--time is required (with --waypoint" in capsys.readouterr().err


def test_a_waypoint_of_a_plan_made_elsewhere_is_noted(tmp_path, capsys):
    plan = _one_waypoint_plan(tmp_path, site=(37.1, -2.36))
    assert main(["simulate", "--waypoint", f"{plan}:0", "--size", "16x16", "--out", str(tmp_path / "a.tiff")]) == 0
    assert "note: the plan was made for a site at 37.1, -2.36 deg, not --site" in capsys.readouterr().err
