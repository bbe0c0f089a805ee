"""The JSON of ``pihim sky``, ``ground``, ``windows``, ``simulate``, ``demo`` and ``calibrate-polarizer`` against
the schemas in ``pihim/schemas`` (run in-process on small inputs), and negative checks so the schemas are not vacuous.

``pihim demo`` runs once for the module at 1224x1024 with one pair (about 10 s; at 612x512 no facet is used), and
once at 256x256, where no outline edge is judged.
"""

from __future__ import annotations

import contextlib
import copy
import fnmatch
import io
import json
import tomllib
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import tifffile

from pihim.cli import main

jsonschema = pytest.importorskip("jsonschema")

NAMES = ("sky", "ground", "windows", "simulate-summary", "demo", "analyser")
IDS = {"sky": "pihim.sky/1", "ground": "pihim.ground/1", "windows": "pihim.windows/1",
       "simulate-summary": "pihim.simulate-summary/1", "demo": "pihim.demo/2", "analyser": "pihim.analyser/1"}
TIME = "2021-05-13T13:00-06:00"


def _schema(name: str) -> dict:
    schema = json.loads(resources.files("pihim").joinpath(f"schemas/{name}.schema.json").read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    return schema


def _errors(doc: dict, name: str) -> list:
    return list(jsonschema.Draft202012Validator(_schema(name)).iter_errors(doc))


def _check(doc: dict, name: str) -> None:
    schema = _schema(name)
    assert schema["$id"] == IDS[name]
    assert doc["schema"] == schema["$id"]
    jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)


def _run(argv: list[str]) -> dict:
    """Run ``pihim ARGV`` in-process; the one JSON line it prints on stdout."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    assert rc in (0, None), err.getvalue()
    lines = out.getvalue().strip().splitlines()
    assert len(lines) == 1, out.getvalue()
    return json.loads(lines[0])


# --------------------------------------------------------------------------- records (one run per module)


@pytest.fixture(scope="module")
def sky_docs(tmp_path_factory) -> list[dict]:
    d = tmp_path_factory.mktemp("sky")
    return [
        _run(["sky", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "10", "--out", str(d / "a"),
              "--json"]),
        _run(["sky", "--time", "2021-05-13T10:00-06:00", "--model", "berry", "--resolution", "10",
              "--out", str(d / "b"), "--json"]),
    ]


@pytest.fixture(scope="module")
def ground_docs(tmp_path_factory) -> list[dict]:
    d = tmp_path_factory.mktemp("ground")
    return [
        _run(["ground", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "10", "--out", str(d / "a"),
              "--json"]),
        _run(["ground", "--time", "2021-05-13T10:00-06:00", "--model", "berry", "--resolution", "10", "--monte-carlo",
              "--facets", "1000", "--out", str(d / "b"), "--json"]),
    ]


@pytest.fixture(scope="module")
def windows_docs(tmp_path_factory) -> list[dict]:
    d = tmp_path_factory.mktemp("windows")
    return [
        # the NSTTF: with the paper's windows for comparison
        _run(["windows", "--date", "2021-05-13", "--step-min", "120", "--out", str(d / "a"), "--json"]),
        # polar night at a custom site: no sample, so nulls everywhere they can be
        _run(["windows", "--date", "2021-12-21", "--site", "85,20,0", "--step-min", "240", "--relative", "--no-shift",
              "--out", str(d / "b"), "--json"]),
    ]


@pytest.fixture(scope="module")
def simulate_docs(tmp_path_factory) -> list[dict]:
    d = tmp_path_factory.mktemp("simulate")
    common = ["--time", TIME, "--size", "64x48", "--supersample", "1", "--json"]
    return [
        _run(["simulate", "--hua", "8E3", "--target", "7E3", *common, "--out", str(d / "a" / "F.tiff")]),
        _run(["simulate", "--camera", "0,-60,20", "--look-at", "0,0,0", *common, "--out", str(d / "b" / "F.tiff")]),
    ]


@pytest.fixture(scope="module")
def demo_doc(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("demo") / "DIR"
    doc = _run(["demo", "--out", str(out), "--pairs", "1", "--size", "1224x1024", "--json"])
    assert json.loads((out / "demo.json").read_text()) == doc
    return doc


@pytest.fixture(scope="module")
def analyser_docs(tmp_path_factory) -> list[dict]:
    """Calibrations of six small synthetic frames behind an ideal polarizer at 0, 30, ..., 150 deg."""
    from pihim.polarimetry import stokes_from_dolp_aop
    from pihim.render import mosaic_from_stokes

    d = tmp_path_factory.mktemp("calibrate")
    rng = np.random.default_rng(0)
    paths = []
    for j, a in enumerate(np.arange(0.0, 180.0, 30.0)):
        frame = mosaic_from_stokes(*stokes_from_dolp_aop(np.full((48, 64), 3000.0), 1.0, a), dark_level=64,
                                   read_noise_dn=2.5, electrons_per_dn=2.0, rng=rng)
        paths.append(d / f"pol_{j}.tiff")
        tifffile.imwrite(paths[-1], frame.astype(np.uint16))
    docs = []
    for extra in ([], ["--fit-drift"]):
        out = d / f"calib{len(docs)}.json"
        doc = _run(["calibrate-polarizer", *map(str, paths), "--angles", "0:180:30", "--dark-level", "64",
                    "--out", str(out), "--json", *extra])
        assert json.loads(out.read_text()) == doc  # stdout carries the file's record
        docs.append(doc)
    return docs


# --------------------------------------------------------------------------- the outputs validate


def test_sky_json(sky_docs) -> None:
    for doc in sky_docs:
        _check(doc, "sky")
    angles, timed = sky_docs
    assert angles["time"] is None and angles["site"] is None and "refraction" not in angles
    assert timed["site"]["name"] == "NSTTF" and timed["model"]["kind"] == "berry"
    assert angles["grid_shape"] == [9, 36]


def test_ground_json(ground_docs) -> None:
    for doc in ground_docs:
        _check(doc, "ground")
    plain, mc = ground_docs
    assert plain["monte_carlo"] is None and "mc_dolp_png" not in plain["files"]
    assert mc["monte_carlo"] == {"facets": 1000, "seed": 0} and "mc_dolp_png" in mc["files"]


def test_windows_json(windows_docs) -> None:
    for doc in windows_docs:
        _check(doc, "windows")
    nsttf, night = windows_docs
    assert nsttf["n_times"] > 0 and "paper_agreement" in nsttf
    assert night["n_times"] == 0 and night["best"] is None and "paper_agreement" not in night
    assert night["settings"]["shift_search"] is None


def test_simulate_summary_json(simulate_docs) -> None:
    for doc in simulate_docs:
        _check(doc, "simulate-summary")
    pair, look = simulate_docs
    assert (pair["hua"], pair["target"]) == ("8E3", "7E3") and (look["hua"], look["target"]) == (None, None)


def test_demo_json(demo_doc) -> None:
    _check(demo_doc, "demo")
    (pair,) = demo_doc["pairs"]
    assert "score" in pair  # the scored form, not the error form, is what this run checks


def test_demo_json_when_no_edge_is_judged(tmp_path) -> None:
    """A 256x256 crop judges no outline edge: ``min_edge_coverage`` is null (a NaN stopped the demo before)."""
    doc = _run(["demo", "--out", str(tmp_path / "d"), "--pairs", "1", "--size", "256x256", "--json"])
    _check(doc, "demo")
    success = doc["pairs"][0]["score"]["edge_success"]
    assert all(v["edges_judged"] == 0 and v["min_edge_coverage"] is None for v in success.values())
    assert json.loads((tmp_path / "d" / "demo.json").read_text()) == doc


def test_calibrate_polarizer_json(analyser_docs) -> None:
    for doc in analyser_docs:
        _check(doc, "analyser")
    assert [d["calibration"]["fit_frame_scale"] for d in analyser_docs] == [False, True]


def test_bare_analyser_matrix_record_validates() -> None:
    """The same id marks AnalyserMatrix.to_dict() (e.g. in a sensor model): no diattenuation, no calibration."""
    from pihim.polarimetry import AnalyserMatrix

    bare = AnalyserMatrix.from_parameters([1.0, 46.0, 89.0, 136.0], [1.0, 0.9, 1.1, 1.0], [100.0, 200.0, 300.0, 400.0])
    _check(bare.to_dict(), "analyser")
    _check(AnalyserMatrix.ideal().to_dict(), "analyser")


def test_schema_ids_match_the_code() -> None:
    import pihim.demo
    from pihim.cli import ground, simulate, sky, windows
    from pihim.polarimetry import analyser

    assert {sky.SCHEMA_ID, ground.SCHEMA_ID, windows.SCHEMA_ID, simulate.SUMMARY_SCHEMA_ID, pihim.demo.SCHEMA_ID,
            analyser._SCHEMA_ID} == set(IDS.values())
    for name in NAMES:
        assert _schema(name)["$id"] == IDS[name]


def test_schemas_are_package_data() -> None:
    """pyproject's package-data globs cover the new schema files, so that wheels ship them."""
    root = Path(__file__).resolve().parents[2]
    pyproject = root / "pyproject.toml"
    if not pyproject.is_file():
        pytest.skip("not run from a source tree")
    globs = tomllib.loads(pyproject.read_text(encoding="utf-8"))["tool"]["setuptools"]["package-data"]["pihim"]
    for name in NAMES:
        rel = f"schemas/{name}.schema.json"
        assert (root / "src" / "pihim" / rel).is_file()
        assert any(fnmatch.fnmatch(rel, g) for g in globs), rel


# --------------------------------------------------------------------------- the schemas reject broken records


def _without(doc: dict, *path: str | int) -> dict:
    bad = copy.deepcopy(doc)
    node = bad
    for key in path[:-1]:
        node = node[key]
    del node[path[-1]]
    return bad


def _with(doc: dict, value: object, *path: str | int) -> dict:
    bad = copy.deepcopy(doc)
    node = bad
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return bad


def _mutations(name: str, doc: dict) -> list[tuple[str, dict]]:
    """Broken copies of a valid record: a required key removed, a wrong type, a value out of range, ..."""
    common = [
        ("no schema", _without(doc, "schema")),
        ("wrong schema id", _with(doc, "pihim.other/1", "schema")),
        ("unknown key", _with(doc, 1, "not_a_field")),
        ("not an object", [doc]),
    ]
    specific: dict[str, Callable[[], list[tuple[str, dict]]]] = {  # built only for ``name``: keys differ
        "sky": lambda: [
            ("no dolp_max", _without(doc, "dolp_max")),
            ("sun as a string", _with(doc, "overhead", "sun")),
            ("DoLP above 1", _with(doc, 1.5, "dolp_max", "value")),
            ("grid_shape of 3", _with(doc, [9, 36, 1], "grid_shape")),
            ("unknown model", _with(doc, "mie", "model", "kind")),
            ("berry without separation", _with(doc, "berry", "model", "kind")),
            ("no npz", _without(doc, "files", "npz")),
        ],
        "ground": lambda: [
            ("no fraction_usable", _without(doc, "fraction_usable")),
            ("fraction as a string", _with(doc, "0.5", "fraction_mirror_shows_ground")),
            ("AoP difference above 90", _with(doc, {"value_deg": 120.0, "camera_zenith_deg": 10.0,
                                                     "camera_azimuth_deg": 5.0}, "max_aop_difference")),
            ("Monte Carlo without its plot", _with(doc, {"facets": 10, "seed": 0}, "monte_carlo")),
            ("no ground parameters", _without(doc, "ground", "sigma_deg")),
        ],
        "windows": lambda: [
            ("no windows", _without(doc, "windows")),
            ("n_times as a float", _with(doc, 3.5, "n_times")),
            ("window without end", _with(doc, [{"start": "t", "duration_min": 0, "peak_fraction": 0.5,
                                                 "mean_fraction": 0.5}], "windows")),
            ("fraction above 1", _with(doc, {"sky": 1.2, "ground": 0, "either": 0, "planned": 0}, "mean_fractions")),
            ("bad date", _with(doc, "13/05/2021", "date")),
            ("no settings mirror", _without(doc, "settings", "mirror")),
        ],
        "simulate-summary": lambda: [
            ("no files", _without(doc, "files")),
            ("rays as a string", _with(doc, "many", "rays")),
            ("odd width", _with(doc, 63, "width_px")),
            ("bad heliostat name", _with(doc, "helio-1", "hua")),
            ("no exposure gain", _without(doc, "exposure", "gain_dn")),
        ],
        "demo": lambda: [
            ("no summary", _without(doc, "summary")),
            ("pairs as an object", _with(doc, {}, "pairs")),
            ("no pairs", _with(doc, [], "pairs")),
            ("pair without score", _without(doc, "pairs", 0, "score")),
            ("edge coverage above 1", _with(doc, 1.5, "pairs", 0, "score", "edge_success", "S0",
                                            "min_edge_coverage")),
            ("used facet without estimate", _with(doc, [{"id": 1, "used": True, "reason": None, "true_az_mrad": 0.0,
                                                          "true_el_mrad": 0.0}], "pairs", 0, "score", "facets")),
            ("settings pairs 0", _with(doc, 0, "settings", "pairs")),
        ],
        "analyser": lambda: [
            ("no matrix", _without(doc, "matrix")),
            ("3 x 3 matrix", _with(doc, doc["matrix"][:3], "matrix")),
            ("angles as strings", _with(doc, ["0", "45", "90", "135"], "angles_deg")),
            ("extinction ratio below 1", _with(doc, [0.5, None, None, None], "extinction_ratio")),
            ("calibration without diattenuation", _without(doc, "diattenuation")),
            ("drift fitted without scales", _with(doc, True, "calibration", "fit_frame_scale")),
            ("no warnings list", _without(doc, "calibration", "warnings")),
        ],
    }
    return common + specific[name]()


@pytest.mark.parametrize("name, fixture", [("sky", "sky_docs"), ("ground", "ground_docs"), ("windows", "windows_docs"),
                                           ("simulate-summary", "simulate_docs"), ("demo", "demo_doc"),
                                           ("analyser", "analyser_docs")])
def test_broken_records_fail(name, fixture, request) -> None:
    docs = request.getfixturevalue(fixture)
    doc = docs if isinstance(docs, dict) else docs[0]
    assert not _errors(doc, name)
    for what, bad in _mutations(name, doc):
        assert _errors(bad, name), f"{name}: {what} was accepted"


def test_every_required_key_is_required(sky_docs, ground_docs, windows_docs, simulate_docs, demo_doc,
                                        analyser_docs) -> None:
    """Removing any top-level required key of a real record makes it invalid."""
    for name, doc in (("sky", sky_docs[0]), ("ground", ground_docs[0]), ("windows", windows_docs[0]),
                      ("simulate-summary", simulate_docs[0]), ("demo", demo_doc), ("analyser", analyser_docs[0])):
        required = _schema(name)["required"]
        assert set(required) <= set(doc), name
        for key in required:
            assert _errors(_without(doc, key), name), f"{name}: {key} is not required"
