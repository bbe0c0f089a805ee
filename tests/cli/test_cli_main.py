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


def test_ctrl_c_in_a_command_is_one_line_and_status_130(tmp_path, capsys, monkeypatch):
    """typer returns 130 for a KeyboardInterrupt and says nothing; the CLI says it was stopped."""
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sky_cli, "sky_map", interrupted)
    assert main([*ARGS, "--out", str(tmp_path / "s")]) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["pihim: aborted"]


@pytest.mark.parametrize("stop, status, line", [(KeyboardInterrupt(), 130, "pihim: aborted"),
                                                 ("terminated", 143, "pihim: terminated")])
def test_an_interrupt_wrapped_by_compiled_code_is_an_interrupt(tmp_path, capsys, monkeypatch, stop, status, line):
    """Ctrl-C (or SIGTERM) while a numba function calls back into Python arrives as a SystemError caused by it."""
    from pihim.cli import Terminated

    interrupt = Terminated(15) if stop == "terminated" else stop

    def fail(*args, **kwargs):
        try:
            raise interrupt
        except BaseException as exc:
            raise SystemError("CPUDispatcher(<function solve>) returned a result with an exception set") from exc

    monkeypatch.setattr(sky_cli, "sky_map", fail)
    monkeypatch.delenv("PIHIM_TRACEBACK", raising=False)
    assert main([*ARGS, "--out", str(tmp_path / "s")]) == status
    assert capsys.readouterr().err.strip().splitlines() == [line]
    assert not (tmp_path / "s").exists()


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


def test_command_table_help_is_the_docstring_summary():
    """``pihim --help`` lists each command from the table; the line must be its docstring's first paragraph."""
    import inspect

    from pihim.cli import COMMANDS, load_command

    import typer

    for name, (_, _, short) in COMMANDS.items():
        target = load_command(name)
        text = target.info.help if isinstance(target, typer.Typer) else inspect.getdoc(target)
        summary = text.split("\n\n")[0]
        assert " ".join(summary.split()) == short, name


def test_help_imports_no_command_and_no_heavy_library():
    """``pihim --help`` imports no command module, nor numpy, numba, scipy, pandas or matplotlib."""
    import os
    import subprocess
    import sys

    code = ("import sys; from pihim.cli import main; rc = main(['--help']); "
            "print(sorted(m for m in sys.modules if m.startswith('pihim.cli.') or m.split('.')[0] in "
            "('numpy', 'numba', 'scipy', 'pandas', 'matplotlib', 'pvlib', 'cv2')), rc, file=sys.stderr)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert "polar" in proc.stdout and "canting" in proc.stdout
    assert proc.stderr.strip().splitlines()[-1] == "[] 0"


def test_command_help_imports_no_heavy_library():
    """``pihim CMD --help`` builds the page from the command's signature: no command imports scipy, numba,
    matplotlib, pandas, OpenCV or tifffile for it (0.1-0.5 s of CPU each, loaded when the command runs)."""
    import os
    import subprocess
    import sys

    code = ("import contextlib, io, sys; from pihim.cli import COMMANDS, main\n"
            "heavy = ('scipy', 'numba', 'matplotlib', 'pandas', 'pvlib', 'cv2', 'tifffile')\n"
            "for name in COMMANDS:\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n"
            "        rc = main([name, '--help'])\n"
            "    print(name, rc, sorted({m.split('.')[0] for m in sys.modules} & set(heavy)), file=sys.stderr)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    lines = proc.stderr.strip().splitlines()
    from pihim.cli import COMMANDS

    assert [line.split()[0] for line in lines] == list(COMMANDS), proc.stderr
    assert all(line.split(maxsplit=1)[1] == "0 []" for line in lines), proc.stderr


def test_each_command_loads_only_its_own_module(capsys):
    """A command's own help page is built from its function (options appear), through the lazy table."""
    from pihim.cli import main

    assert main(["windows", "--help"]) == 0
    assert "--step-min" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [[], ["campaign"]])
def test_no_command_prints_the_help_and_one_error_line(capsys, argv):
    """``pihim`` (or ``pihim campaign``) alone: the help on stdout, one line on stderr, exit status 2."""
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert "Usage" in out
    assert err.strip().splitlines() == ["pihim: error: no command given (listed above)"]


def test_a_json_only_run_imports_no_rich(tmp_path):
    """``pihim polar FRAME --json`` prints JSON alone: rich (15-20 ms of CPU to import) is left unloaded; the
    console on stderr is made when a command first prints to it."""
    import json
    import os
    import subprocess
    import sys

    import numpy as np
    import tifffile

    frame = tmp_path / "frame.tiff"
    tifffile.imwrite(frame, np.arange(64 * 48, dtype=np.uint16).reshape(48, 64) % 4096)
    code = ("import sys; from pihim.cli import main; rc = main(sys.argv[1:]); "
            "print(rc, 'rich' in sys.modules, file=sys.stderr)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.run([sys.executable, "-c", code, "polar", str(frame), "--out", str(tmp_path / "out"), "--json"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.stderr.strip().splitlines()[-1] == "0 False", proc.stderr[-300:]
    assert json.loads(proc.stdout.splitlines()[0])["status"] == "ok"
