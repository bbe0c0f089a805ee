"""Huge finite values and outputs that are inputs: one line and exit status 2, no numpy warning, nothing written.

Found by a fuzzing audit: ``1e308`` in a length or a noise sigma overflowed the geometry (numpy's overflow warnings
on stderr, meaningless files with exit status 0, or an "internal error"), and a calibration's ``--out`` naming one
of its input images replaced that image.
"""

from __future__ import annotations

import sys

import pytest

import pihim.cli as cli_module
from pihim.cli import main

TIME = "2021-05-13T13:00-06:00"


def _refused(capsys, argv, needle):
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("pihim: error: ") and needle in err[0], err


@pytest.mark.parametrize("argv, needle", [
    (["plan", "--time", TIME, "--heliostats", "8E3", "--max-altitude", "1e308"], "maximum altitude must be in (0, 1000]"),
    (["windows", "--date", "2021-05-13", "--max-altitude", "1e308"], "--max-altitude must be in (0, 1000]"),
    (["plan", "--time", TIME, "--heliostats", "8E3", "--aim", "1e308,0,30"], "--aim: coordinates must be within"),
    (["windows", "--date", "2021-05-13", "--aim", "1e308,0,30"], "--aim: coordinates must be within"),
    (["windows", "--date", "2021-05-13", "--min-elevation", "89"], "--min-elevation must be in [0, 89) deg"),
    (["ground", "--sun-zenith", "30", "--sun-azimuth", "0", "--mirror-normal-azimuth", "inf"],
     "--mirror-normal-azimuth must be in [-360, 360] deg, got inf"),
])
def test_planning_and_physics_options(tmp_path, capsys, argv, needle):
    out = tmp_path / "o"
    _refused(capsys, [*argv, "--out", str(out)], needle)
    assert not out.exists()


@pytest.mark.parametrize("option, needle", [
    (["--gps-sigma-m", "1e308"], "GPS sigma (m) must be at most 1000"),
    (["--attitude-sigma-deg", "1e308"], "attitude sigma (deg) must be at most 180"),
    (["--canting-sigma-mrad", "1e308"], "canting sigma (mrad) must be at most 1000"),
    (["--tracking-sigma-mrad", "1e308"], "tracking sigma (mrad) must be at most 1000"),
    (["--blur-sigma-px", "1e308"], "blur sigma (px) must be at most 100"),
    (["--camera", "1e308,0,30", "--look-at", "0,60,0"], "--camera: coordinates must be within"),
])
def test_simulate_noise_and_camera(tmp_path, capsys, option, needle):
    pose = [] if "--camera" in option else ["--hua", "8E3", "--target", "7E3"]
    out = tmp_path / "o" / "f.tiff"
    _refused(capsys, ["simulate", "--time", TIME, *pose, *option, "--size", "64x48", "--out", str(out)], needle)
    assert not out.exists()


@pytest.fixture
def frame(tmp_path):
    import numpy as np
    import tifffile

    path = tmp_path / "frame.tiff"
    tifffile.imwrite(path, np.full((16, 16), 500, np.uint16))
    return path


@pytest.mark.parametrize("option, needle", [
    (["--dark-level", "1e308"], "--dark-level must be a raw level in [0, 65535]"),
    (["--saturation-level", "1e308"], "--saturation-level must be a raw level above --dark-level (0) and at most 65535"),
])
def test_polar_levels(tmp_path, capsys, frame, option, needle):
    out = tmp_path / "o"
    _refused(capsys, ["polar", str(frame), *option, "--out", str(out)], needle)
    assert not out.exists()


def test_calibrate_polarizer_bounds(tmp_path, capsys):
    frames = [str(tmp_path / f"p{k}.tiff") for k in range(4)]  # refused before any frame is read
    base = ["calibrate-polarizer", *frames, "--out", str(tmp_path / "c.json")]
    _refused(capsys, [*base, "--angles", "0,45,1e308,135"], "--angles: polarizer angles must be within +-1e+06 deg")
    _refused(capsys, [*base, "--angles", "0:180:45", "--dark-level", "1e308"],
             "--dark-level must be a raw level in [0, 65535]")
    assert not (tmp_path / "c.json").exists()


def test_calibrate_camera_bounds(tmp_path, capsys):
    images = [str(tmp_path / f"v{k}.png") for k in range(3)]  # refused before any image is read
    base = ["calibrate-camera", *images, "--grey", "--out", str(tmp_path / "c.json")]
    _refused(capsys, [*base, "--board", "99999999999999999999x6", "--square", "25"], "--board: at most 1000x1000")
    _refused(capsys, [*base, "--board", "9x6", "--square", "1e308"], "--square must be a positive number")
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("command", ["calibrate-polarizer", "calibrate-camera"])
def test_a_calibration_never_replaces_its_input(tmp_path, capsys, command):
    inputs = [tmp_path / f"in{k}.tiff" for k in range(4)]
    for k, p in enumerate(inputs):
        p.write_bytes(b"an input image %d" % k)
    victim = tmp_path / "sub" / ".." / "in2.tiff"  # another spelling of an input
    (tmp_path / "sub").mkdir()
    opts = ["--angles", "0:180:45"] if command == "calibrate-polarizer" else ["--grey", "--board", "9x6", "--square", "25"]
    _refused(capsys, [command, *map(str, inputs), *opts, "--out", str(victim)], "writing it would replace that input")
    assert [p.read_bytes() for p in inputs] == [b"an input image %d" % k for k in range(4)]


@pytest.mark.parametrize("argv", [
    ["sky", "--sun-zenith", "30", "--sun-azimuth", "235", "--out", ""],
    ["plan", "--time", TIME, "--out="],
    ["calibrate-polarizer", "f.tiff", "--angles", "0,45,90,135", "-o", ""],
    ["canting", "f.tiff", "--meta", "", "--out", "x"],
    ["live", "--source", "synthetic", "--record", ""],
])
def test_empty_path_option_is_refused(tmp_path, capsys, monkeypatch, argv):
    # typer turns '' into Path('.'): '--out ""' wrote into the working directory
    monkeypatch.chdir(tmp_path)
    option = next(a.partition("=")[0] for k, a in enumerate(argv)
                  if a.endswith("=") or (k + 1 < len(argv) and argv[k + 1] == ""))
    _refused(capsys, argv, f"{option} needs a path, got an empty string")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    ["plan", "--time", TIME, "--field", "", "--out", "o"],
    ["windows", "--date", "2021-05-13", "--field", " ", "--out", "o"],
])
def test_empty_field_is_named(tmp_path, capsys, monkeypatch, argv):
    # '' became Path('.'): "--field .: is a directory, not a heliostat CSV file"
    monkeypatch.chdir(tmp_path)
    _refused(capsys, argv, "--field is empty: give nsttf-like or a heliostat CSV file")
    assert list(tmp_path.iterdir()) == []


def test_empty_field_is_named_for_a_campaign():
    from pihim.cli.campaign import _field_spec
    from pihim.errors import PihimInputError

    with pytest.raises(PihimInputError, match="--field is empty"):
        _field_spec("", None)
    assert _field_spec("NSTTF", None) == ("nsttf-like", None)


def _commands(cmd, path=()):
    """Every (sub)command of the CLI, as (names, click command)."""
    import typer

    if isinstance(cmd, typer.core.TyperGroup):
        for name in cmd.list_commands(None):
            sub = cmd.get_command(None, name)
            sub = sub.real() if isinstance(sub, cli_module.LazyCommand) else sub
            yield from _commands(sub, (*path, name))
    else:
        yield path, cmd


def _is_path(hint) -> bool:
    import pathlib
    import types
    import typing

    if typing.get_origin(hint) is typing.Annotated:
        return _is_path(typing.get_args(hint)[0])
    if typing.get_origin(hint) in (typing.Union, types.UnionType, list):
        return any(_is_path(a) for a in typing.get_args(hint))
    return hint is pathlib.Path


def test_the_empty_path_check_knows_every_path_option():
    """The options refused with an empty value (``_PATH_OPTIONS``, kept by hand) are exactly those annotated as
    paths in the commands' signatures: a new path option must be added to the list."""
    import inspect
    import typing

    found = set()
    for _, cmd in _commands(cli_module._command()):
        hints = typing.get_type_hints(inspect.unwrap(cmd.callback), include_extras=True)
        found |= {o for p in cmd.params if p.param_type_name == "option" and _is_path(hints[p.name])
                  for o in p.opts + p.secondary_opts}
    assert "--out" in found and "--store" in found
    assert found == cli_module._PATH_OPTIONS


@pytest.mark.parametrize("argv, name", [
    (["polar", ""], "FRAMES"),
    (["polar", "a.tiff", "", "--out", "o"], "FRAMES"),
    (["polar", "--json", "", "--out=o"], "FRAMES"),  # --json is a flag: '' is a frame
    (["polar", "--out", "o", "--", ""], "FRAMES"),
    (["edges", "", "--out", "o"], "FRAME"),
    (["calibrate-camera", "", "--out", "c.json"], "IMAGE"),
    (["campaign", "report", "", "--out", "o"], "STORE"),
])
def test_empty_positional_path_is_refused(tmp_path, capsys, monkeypatch, argv, name):
    # typer turns '' into Path('.'): 'pihim polar ""' was reported as ".: is a directory"
    monkeypatch.chdir(tmp_path)
    _refused(capsys, argv, f"{name} needs a path, got an empty string")
    assert list(tmp_path.iterdir()) == []


def test_empty_option_value_is_left_to_the_command(tmp_path, capsys, monkeypatch):
    # '' as the value of an option that takes one is not a positional argument
    monkeypatch.chdir(tmp_path)
    _refused(capsys, ["plan", "--heliostats", "", "--time", TIME, "--out", "o"], "--heliostats names no heliostat")


@pytest.mark.parametrize("argv, needle", [
    (["polar", "--bogus", ""], "No such option: --bogus"),  # an unknown option is the parser's to report
    (["edges", "x.tiff", "", "--out", "o"], "unexpected extra argument"),  # so is an extra argument
])
def test_an_empty_argument_the_command_does_not_take_is_left_to_the_parser(tmp_path, capsys, monkeypatch, argv,
                                                                            needle):
    monkeypatch.chdir(tmp_path)
    _refused(capsys, argv, needle)


def test_an_empty_argument_to_a_command_that_cannot_load_is_a_one_line_error(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pihim.cli.edges", None)  # a command module that fails to import
    monkeypatch.setattr(cli_module, "_COMMAND", {})
    assert main(["edges", "", "--out", "o"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: internal error (ModuleNotFoundError"), err
