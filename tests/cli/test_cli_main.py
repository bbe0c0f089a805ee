"""The safety net of ``pihim.cli.main``: one stderr line and an exit status, never a traceback."""

import pytest

import pihim.cli.sky as sky_cli
from pihim.cli import main

ARGS = ["sky", "--sun-zenith", "30", "--sun-azimuth", "10", "--resolution", "10"]


@pytest.mark.parametrize(
    "exc, status, needle",
    [
        (RuntimeError("boom\nsecond line"), 1, "internal error (RuntimeError: boom second line)"),
        (OSError(5, "Input/output error", "/some/file"), 1, "/some/file: Input/output error"),
        (MemoryError(), 2, "not enough memory"),
        (RecursionError(), 2, "nested too deeply"),
    ],
)
def test_unexpected_failures_are_one_line(tmp_path, capsys, monkeypatch, exc, status, needle):
    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr(sky_cli, "sky_map", fail)
    monkeypatch.delenv("PIHIM_TRACEBACK", raising=False)
    assert main([*ARGS, "--out", str(tmp_path / "s")]) == status
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error:") and needle in err[0]


def test_traceback_on_request(tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(sky_cli, "sky_map", fail)
    monkeypatch.setenv("PIHIM_TRACEBACK", "1")
    with pytest.raises(RuntimeError, match="boom"):
        main([*ARGS, "--out", str(tmp_path / "s")])


def test_sigterm_handler_is_restored(tmp_path, capsys):
    import signal

    before = signal.getsignal(signal.SIGTERM)
    assert main([*ARGS, "--out", str(tmp_path / "s")]) == 0
    assert signal.getsignal(signal.SIGTERM) is before
