"""``pihim live`` option checks: bad input is one line and exit 2 before the port, a camera or a folder is touched."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import pihim
from pihim.cli import main

BASE = ["live", "--source", "synthetic", "--size", "64x48", "--duration", "2", "--port", "0"]


@pytest.fixture
def no_serving(monkeypatch):
    """Fail the test, rather than serve for --duration, if the options get past validation."""
    import pihim.live.server as server_mod

    def serve(engine, sock, **kwargs):
        sock.close()
        raise AssertionError("the server was started")

    monkeypatch.setattr(server_mod, "serve", serve)


@pytest.mark.parametrize(("options", "named", "says"), [
    (["--exposure-us", "1e308"], "--exposure-us", "at most 10000000 us"),
    (["--max-exposure-us", "1e9"], "--max-exposure-us", "at most 10000000 us"),
    (["--exposure-us", "50000", "--max-exposure-us", "1000"], "--exposure-us 50000", "above --max-exposure-us 1000"),
    (["--exposure-us", "30000"], "--exposure-us 30000", "above --max-exposure-us 20000"),  # the default maximum
    (["--bit-depth", "0"], "--bit-depth", "1..16, got 0"),
    (["--bit-depth", "17"], "--bit-depth", "1..16, got 17"),
    (["--bit-depth", "8", "--dark-level", "255"], "--dark-level 255", "8-bit full scale"),
    (["--dark-level", "70000"], "--dark-level", "[0, 65535], got 70000"),  # served nothing, exit 0
    (["--field", "/nonexistent/pihim-fuzz/nope.csv"], "--field", "nope.csv"),
    (["--max-gain-db", "1e308"], "--max-gain-db", "at most 100 dB"),
    (["--host", "x" * 64 + ".invalid"], "--host xxx", "cannot resolve"),  # (a 64-letter label fails without DNS)
    # options of other sources were silently ignored
    (["--pixel-format", "mono8"], "--pixel-format", "does not apply to a synthetic source"),
    (["--width", "10", "--height", "8"], "--width and --height", "do not apply to a synthetic source"),
], ids=["exposure-huge", "max-exposure-huge", "exposure-above-max", "exposure-above-default-max", "bit-depth-0",
        "bit-depth-17", "dark-level-at-full-scale", "dark-level-huge", "field-missing", "max-gain-huge", "host-unresolvable",
        "pixel-format-synthetic", "raw-size-synthetic"])
def test_bad_option_is_one_line_exit_2(tmp_path, capsys, no_serving, options, named, says):
    captures, record = tmp_path / "captures", tmp_path / "rec"
    rc = main([*BASE, "--captures", str(captures), "--record", str(record), *options])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("pihim: error: "), err
    assert named in err[0] and says in err[0], err[0]
    assert not captures.exists() and not record.exists()


def test_exposure_above_max_is_fine_without_the_controller(tmp_path, capsys, monkeypatch):
    """--max-exposure-us bounds the controller: with --no-auto-exposure a longer first exposure is accepted."""
    import pihim.live.server as server_mod

    seen = {}

    def serve(engine, sock, **kwargs):
        sock.close()
        seen["settings"] = engine.config.initial_settings
        return None

    monkeypatch.setattr(server_mod, "serve", serve)
    assert main([*BASE, "--captures", str(tmp_path / "c"), "--exposure-us", "50000", "--no-auto-exposure"]) == 0
    assert seen["settings"].exposure_us == 50000.0


def test_a_folder_replay_takes_any_first_exposure(tmp_path, frame_folder, monkeypatch):
    """--max-exposure-us bounds the controller's commands: a folder of frames takes none, so it is not checked."""
    import pihim.live.server as server_mod

    monkeypatch.setattr(server_mod, "serve", lambda engine, sock, **kwargs: sock.close())
    assert main(["live", "--source", str(frame_folder), "--duration", "2", "--port", "0", "--captures",
                 str(tmp_path / "c"), "--exposure-us", "50000", "--max-exposure-us", "1000"]) == 0


def test_sigterm_says_terminated(tmp_path):
    """SIGTERM while serving: the --json summary, ``pihim: terminated`` on stderr, status 143 (docs/cli.md)."""
    env = {**os.environ, "PYTHONPATH": str(Path(pihim.__file__).resolve().parents[1])}  # the pihim imported here
    cmd = [sys.executable, "-m", "pihim", *BASE[:-4], "--port", "0", "--duration", "60", "--json",
           "--captures", str(tmp_path / "c")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    try:
        line = proc.stderr.readline()  # "pihim live: ... at http://127.0.0.1:PORT/ (Ctrl-C to stop)"
        assert line.startswith("pihim live: "), line + proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert err.strip().splitlines() == ["pihim: terminated"]
    assert '"stopped_by": "SIGTERM"' in out
