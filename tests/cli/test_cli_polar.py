"""End-to-end tests of ``pihim polar`` and the atomic-output guarantee."""

import contextlib
import json
import os
from importlib import resources
from pathlib import Path

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
    assert sorted(p.name for p in out.iterdir()) == [
        "frame_a.AoP.tiff", "frame_a.DoLP.tiff", "frame_a.S0.tiff", "frame_a.polar.json"]


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--layout", "0,45,90"], "layout"),
        (["--demosaic", "nearest"], "demosaic"),
        (["--calibration", "nope.json"], "calibration"),
        (["--bogus-option"], "bogus"),
        # issue 10: out-of-range numbers are one line and exit 2, before any frame is read
        (["--layout", "inf,45,90,135"], "whole degrees"),
        (["--layout", "0.7,45.9,90.2,135.1"], "whole degrees"),
        (["--saturation-level", "nan"], "saturation-level"),
        (["--saturation-level", "-1"], "saturation-level"),
        (["--dark-level", "nan"], "dark-level"),
        (["--dark-level", "-3"], "dark-level"),
        (["--bit-depth", "0"], "bit-depth"),
        (["--bit-depth", "12", "--saturation-level", "5000"], "full scale"),
        (["--pixel-format", "Mono13"], "pixel format"),
        (["--dark-level", "-10"], "--dark-level must be a raw level in [0, 65535], got -10"),
    ],
)
def test_bad_options_one_line_exit_2(frame, tmp_path, capsys, extra, needle):
    rc = main(["polar", str(frame), "--out", str(tmp_path / "o"), *extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and needle in err.lower()
    assert not (tmp_path / "o").exists()


def test_same_stems_get_distinct_output_names(frame, tmp_path, capsys):
    other = tmp_path / "frame_a.tiff"
    other.write_bytes(frame.read_bytes())
    out = tmp_path / "o"
    assert main(["polar", str(frame), str(other), "--out", str(out), "--json"]) == 0
    recs, err = _records(capsys)
    assert [r["status"] for r in recs] == ["ok", "ok"]
    s0 = [r["outputs"]["S0"] for r in recs]
    assert len(set(s0)) == 2 and all(p.endswith(".S0.tiff") for p in s0)
    assert all(tifffile.imread(p).shape == (16, 20) for p in s0)
    # one warning line names both frames and their output names
    warning = [ln for ln in err.splitlines() if "share the name" in ln]
    assert len(warning) == 1 and str(frame) in warning[0] and str(other) in warning[0]
    # the names are stable: a rerun finds both frames done
    assert main(["polar", str(frame), str(other), "--out", str(out), "--json"]) == 0
    recs, _ = _records(capsys)
    assert [r.get("resumed") for r in recs] == [True, True]


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


# -- issue 10: every failure contained --------------------------------------------------------------


def test_out_folder_under_a_file_is_one_line(frame, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["polar", str(frame), "--out", str(afile / "sub")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: --out") and "not a directory" in err[0]


def test_unreadable_items_do_not_stop_the_batch(frame, tmp_path, capsys):
    folder = tmp_path / "in" / "folder.tiff"  # a directory named like a frame
    folder.mkdir()
    fifo = tmp_path / "in" / "x.raw"
    os.mkfifo(fifo)  # reading it would block forever
    out = tmp_path / "o"
    rc = main(["polar", str(folder), str(fifo), str(frame), "--width", "40", "--height", "32", "--out", str(out),
               "--json"])
    recs, err = _records(capsys)
    assert rc == 2
    assert [r["status"] for r in recs] == ["error", "error", "ok"]
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("pihim: error:")]
    assert len(errors) == 2 and "directory" in errors[0] and "not a regular file" in errors[1]
    assert (out / "frame_a.S0.tiff").is_file()


def test_memory_error_on_one_frame_spares_the_next(frame, tmp_path, capsys, monkeypatch):
    import pihim.cli.polar as polar_cli

    big = tmp_path / "in" / "big.tiff"
    big.write_bytes(frame.read_bytes())
    later = tmp_path / "in" / "later.tiff"
    later.write_bytes(frame.read_bytes())
    real = polar_cli.polar_image

    def polar_image(data, **kw):
        if polar_image.calls == 1:  # the second frame of the batch
            polar_image.calls += 1
            raise MemoryError
        polar_image.calls += 1
        return real(data, **kw)

    polar_image.calls = 0
    monkeypatch.setattr(polar_cli, "polar_image", polar_image)
    out = tmp_path / "o"
    assert main(["polar", str(frame), str(big), str(later), "--out", str(out), "--json"]) == 2
    recs, err = _records(capsys)
    assert [r["status"] for r in recs] == ["ok", "error", "ok"]
    assert "not enough memory" in recs[1]["error"] and "big.tiff" in recs[1]["error"]
    assert (out / "later.S0.tiff").is_file() and not list(out.glob("big.*"))
    assert "Traceback" not in err


def test_frame_too_large_for_memory_refused_with_the_figure(frame, tmp_path, capsys, monkeypatch):
    import pihim._resources as resources

    monkeypatch.setattr(resources, "available_memory", lambda: 10_000)  # 10 kB left
    out = tmp_path / "o"
    assert main(["polar", str(frame), "--out", str(out), "--demosaic", "full"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    # 32 x 40 pixels x 80 B = 102 kB needed, 10 kB available
    assert "frame_a.tiff: a 40x32 frame with --demosaic full needs about 102 kB of memory; 10 kB is available" in err[0]
    assert not list(out.glob("frame_a.*"))


def test_never_writes_over_an_input(frame, tmp_path, capsys):
    same = frame.parent
    s0_named = same / "frame_a.S0.tiff"  # the name frame_a's S0 output would take
    s0_named.write_bytes(frame.read_bytes())
    before = s0_named.read_bytes()
    assert main(["polar", str(frame), str(s0_named), "--out", str(same), "--json"]) == 2
    recs, err = _records(capsys)
    assert [r["status"] for r in recs] == ["error", "ok"]
    assert "would overwrite the input" in recs[0]["error"] and str(s0_named) in recs[0]["error"]
    assert s0_named.read_bytes() == before
    assert (same / "frame_a.S0.S0.tiff").is_file()  # the other frame was processed


@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_never_writes_over_the_truth_of_a_simulated_frame(frame, tmp_path, capsys, overwrite):
    """``pihim simulate`` writes FRAME.S0.tiff (rendered truth) beside FRAME.json: polar --out that folder refuses
    the frame rather than replace the truth with its measurement (also with --overwrite, which is for polar's own
    outputs); a FRAME.json of anything else does not stop it."""
    same = frame.parent
    truth = same / "frame_a.S0.tiff"
    tifffile.imwrite(truth, np.ones((32, 40), np.float32))
    before = truth.read_bytes()
    (same / "frame_a.json").write_text(json.dumps({"schema": "pihim.simulated-frame/1", "log": {}, "truth": {}}))
    assert main(["polar", str(frame), "--out", str(same), *overwrite]) == 2
    err = capsys.readouterr().err
    assert "is the rendered truth of" in err and "(pihim simulate); choose another --out" in err
    assert truth.read_bytes() == before
    (same / "frame_a.json").write_text(json.dumps({"schema": "something-else/1"}))
    assert main(["polar", str(frame), "--out", str(same), *overwrite]) == 0
    capsys.readouterr()
    assert tifffile.imread(truth).shape == (16, 20)  # polar's super-pixel S0 now


def test_corrupt_png_is_one_line(tmp_path, capfd):
    import cv2

    ok, buf = cv2.imencode(".png", (np.arange(64 * 64).reshape(64, 64) % 4096).astype(np.uint16))
    data = bytearray(buf.tobytes())
    i = data.index(b"IDAT")
    data[i + 10 : i + 30] = bytes(20)  # corrupt the compressed data, keep the chunk structure
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    assert main(["polar", str(bad), "--out", str(tmp_path / "o" / "deeper")]) == 2
    err = capfd.readouterr().err.strip().splitlines()  # file descriptor 2: libpng writes there itself
    assert len(err) == 1 and err[0].startswith("pihim: error:") and "bad.png" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.png"]  # the --out folders it made are gone again


def test_dark_level_above_every_value_warns_and_says_so_in_json(frame, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["polar", str(frame), "--out", str(out), "--dark-level", "4000", "--json"]) == 0
    recs, err = _records(capsys)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pihim: warning:") and "--dark-level 4000" in lines[0]
    assert recs[0]["fraction_valid"] == 0.0 and "no valid pixel" in recs[0]["warnings"][0]


def test_implausible_calibration_refused(frame, tmp_path, capsys):
    from pihim.polarimetry import AnalyserMatrix

    cal = tmp_path / "tiny.json"
    cal.write_text(json.dumps({"matrix": (AnalyserMatrix.ideal().matrix * 1e-300).tolist()}))
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    for path, needle in ((cal, "transmissions"), (deep, "nested too deeply")):
        assert main(["polar", str(frame), "--out", str(tmp_path / "o"), "--calibration", str(path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and str(path) in err[0]
    assert not (tmp_path / "o").exists()


def test_disk_full_leaves_no_part_of_the_frame(frame, tmp_path, capsys, monkeypatch):
    other = tmp_path / "in" / "frame_b.tiff"
    other.write_bytes(frame.read_bytes())
    import errno

    from pihim import _direct_io  # where the command writes its files

    real = _direct_io._write_all

    def write_all(fd, data):
        name = os.readlink(f"/proc/self/fd/{fd}")  # two writer threads: the frames' files interleave
        if "frame_a.DoLP" in name:  # frame_a's DoLP (its S0 may be written already)
            real(fd, data[:4096])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data)

    monkeypatch.setattr(_direct_io, "_write_all", write_all)
    out = tmp_path / "o"
    assert main(["polar", str(frame), str(other), "--out", str(out), "--json"]) == 1
    recs, err = _records(capsys)
    status = {Path(r["file"]).name: r for r in recs}  # in the order the frames finished
    assert {k: r["status"] for k, r in status.items()} == {"frame_a.tiff": "error", "frame_b.tiff": "ok"}
    failed = status["frame_a.tiff"]
    assert "no space left on the device" in failed["error"] and "requested" not in failed["error"]
    assert sorted(p.name for p in out.iterdir()) == [
        "frame_b.AoP.tiff", "frame_b.DoLP.tiff", "frame_b.S0.tiff", "frame_b.polar.json"]


def _mtimes(out):
    return {p.name: p.stat().st_mtime_ns for p in out.iterdir()}


def test_rerun_resumes_and_overwrite_redoes(frame, tmp_path, capsys):
    other = tmp_path / "in" / "frame_b.tiff"
    other.write_bytes(frame.read_bytes())
    out = tmp_path / "o"
    args = ["polar", str(frame), str(other), "--out", str(out), "--json"]
    assert main(args) == 0
    _records(capsys)
    first = _mtimes(out)
    (out / "frame_b.DoLP.tiff").unlink()  # an incomplete frame is redone
    assert main(args) == 0
    recs, err = _records(capsys)
    assert [r.get("resumed", False) for r in recs] == [True, False]
    assert "1 of 2 frames were already done" in err
    assert all(_mtimes(out)[n] == t for n, t in first.items() if n.startswith("frame_a"))
    # other options: the frame is redone
    assert main([*args, "--demosaic", "full"]) == 0
    recs, _ = _records(capsys)
    assert [r.get("resumed", False) for r in recs] == [False, False] and recs[0]["demosaic"] == "full"
    assert main([*args, "--demosaic", "full", "--overwrite"]) == 0
    recs, _ = _records(capsys)
    assert [r.get("resumed", False) for r in recs] == [False, False]


def test_stale_temporaries_are_removed(frame, tmp_path, capsys):
    import subprocess
    import sys

    from pihim._atomic import _host_tag

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)  # a process that has exited
    out = tmp_path / "o"
    out.mkdir()
    stale = out / f".frame_a.S0.pihim-{_host_tag()}-{pid}-abcdefgh.part.tiff"
    stale.write_bytes(b"half")
    alive = out / f".other.pihim-{_host_tag()}-{os.getpid()}-abcdefgh.part.tiff"  # a run still going
    alive.write_bytes(b"busy")
    elsewhere = out / f".other.pihim-zzzz-{pid}-abcdefgh.part.tiff"  # not a name pihim makes
    elsewhere.write_bytes(b"?")
    assert main(["polar", str(frame), "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    assert stale.name not in names and alive.name in names and elsewhere.name in names


#: A process that imports the CLI once, then forks one child per request running ``main(argv)``: each child is
#: a real ``pihim polar`` process (own pid, own signal handlers) without the seconds of interpreter start-up.
_ZYGOTE = r"""
import json, os, sys
from pihim.cli import main
for line in sys.stdin:
    argv, err_path = json.loads(line)
    pid = os.fork()
    if pid == 0:
        fd = os.open(err_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(fd, 2)
        os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
        rc = main(argv)
        sys.stderr.flush()
        os._exit(rc)
    print(pid, flush=True)
    print(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]), flush=True)
"""


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_killed_batches_resume_without_loss(tmp_path, capsys):
    """Kill a real ``pihim polar`` batch at random moments (SIGKILL twice, then SIGTERM), then rerun.

    Each kill lands at a random moment of the frame after a random number of completed frames (delay drawn
    over the measured duration of a frame). After each: every frame with a record has all its outputs,
    readable and of the right shape; after SIGTERM (exit 143) no temporary is left. After the rerun: no
    temporary, no output without its record, every frame complete and done exactly once (frames complete
    before the rerun are skipped, their files untouched; the others are processed once).
    """
    import random
    import signal
    import subprocess
    import sys
    import time

    random.seed(10)
    rng = np.random.default_rng(10)
    frames = []
    for k in range(5):
        p = tmp_path / "in" / f"f{k:02d}.tiff"
        p.parent.mkdir(exist_ok=True)
        tifffile.imwrite(p, rng.integers(0, 4000, (64, 64), dtype=np.uint16))
        frames.append(p)
    out = tmp_path / "o"
    opts = ["--demosaic", "full", "--png"]  # the captioned figure makes a frame last long enough to be hit
    outputs = ("S0.tiff", "DoLP.tiff", "AoP.tiff", "S0.png", "DoLP.png", "AoP.png", "polar.png")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    zygote = subprocess.Popen([sys.executable, "-c", _ZYGOTE], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              env=env, text=True)

    def records():
        return {p.name.removesuffix(".polar.json") for p in out.glob("*.polar.json")} if out.is_dir() else set()

    try:
        for trial, sig in enumerate((signal.SIGKILL, signal.SIGKILL, signal.SIGTERM)):
            err_path = tmp_path / f"err{trial}.txt"
            zygote.stdin.write(json.dumps([["polar", *map(str, frames), "--out", str(out), *opts],
                                           str(err_path)]) + "\n")
            zygote.stdin.flush()
            pid = int(zygote.stdout.readline())
            # wait for 1-2 frames more than before, timing them, then kill within the next frame
            start, want = time.monotonic(), len(records()) + random.randint(1, 2)
            t_last, n_last, per_frame = start, len(records()), None
            while _alive(pid) and time.monotonic() - start < 60:
                n = len(records())
                if n != n_last:
                    per_frame, t_last, n_last = time.monotonic() - t_last, time.monotonic(), n
                if n >= want:
                    break
                time.sleep(0.005)
            time.sleep(random.uniform(0.0, per_frame or 0.1))
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
            rc = int(zygote.stdout.readline())
            err = err_path.read_text()
            assert "Traceback" not in err
            done = records()
            if sig == signal.SIGTERM and rc == 143:
                assert "pihim: terminated" in err
                assert not [p.name for p in out.iterdir() if ".part" in p.name], "SIGTERM left a temporary file"
            elif sig == signal.SIGTERM:  # the batch had just finished
                assert rc == 0 and len(done) == len(frames)
            else:
                assert rc in (-signal.SIGKILL, 0)
            for stem in done:  # completion is marked last: a frame with a record is whole
                for suffix in outputs:
                    assert (out / f"{stem}.{suffix}").stat().st_size > 0
                assert tifffile.imread(out / f"{stem}.DoLP.tiff").shape == (64, 64)
    finally:
        zygote.stdin.close()
        zygote.wait(timeout=30)
    before = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.iterdir()
              if p.name.split(".")[0] in done}
    assert main(["polar", *map(str, frames), "--out", str(out), *opts, "--json"]) == 0
    recs, _ = _records(capsys)
    assert sorted(r["file"] for r in recs) == sorted(map(str, frames))  # every frame exactly once
    assert {r["file"] for r in recs if r.get("resumed")} == {str(f) for f in frames if f.stem in done}
    assert not [p.name for p in out.iterdir() if ".part" in p.name]  # temporaries of the killed runs removed
    assert records() == {f.stem for f in frames}
    assert {p.name for p in out.iterdir()} == {f"{f.stem}.{s}" for f in frames for s in (*outputs, "polar.json")}
    after = {n: (p.stat().st_ino, p.stat().st_mtime_ns) for n in before if (p := out / n).exists()}
    assert after == before  # frames completed before the rerun were not written again


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


# -- merge of issue 10 and issue 11: the captioned figure in the frame's group, the summary with resumed frames ------


def test_png_figure_belongs_to_the_frame_group(frame, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["polar", str(frame), "--out", str(out), "--png", "--json"]) == 0
    recs, _ = _records(capsys)
    fig = out / "frame_a.polar.png"
    assert recs[0]["outputs"]["figure_png"] == str(fig)
    assert recs[0]["output_bytes"]["figure_png"] == fig.stat().st_size > 20_000
    stored = json.loads((out / "frame_a.polar.json").read_text())
    assert stored["outputs"]["figure_png"] == str(fig)
    # the figure is checked on resume like the other outputs: a truncated figure makes the frame redone
    fig.write_bytes(fig.read_bytes()[:100])
    assert main(["polar", str(frame), "--out", str(out), "--png", "--json"]) == 0
    recs, _ = _records(capsys)
    assert not recs[0].get("resumed") and fig.stat().st_size > 20_000


def test_png_figure_failure_leaves_none_of_the_frame(frame, tmp_path, capsys, monkeypatch):
    import pihim.cli.polar as polar_cli

    other = tmp_path / "in" / "frame_b.tiff"
    other.write_bytes(frame.read_bytes())
    real = polar_cli.polar_figure_png
    seen = []

    def figure(*args, **kw):
        seen.append((args[3], kw.get("atomic")))
        # frame_a's figure, after its TIFFs and bare previews were written (picked by name: with two writer
        # threads either frame's figure can come first)
        if args[3].name.startswith(".frame_a."):
            raise OSError(28, "No space left on device")
        return real(*args, **kw)

    monkeypatch.setattr(polar_cli, "polar_figure_png", figure)
    out = tmp_path / "o"
    assert main(["polar", str(frame), str(other), "--out", str(out), "--png", "--json"]) == 1
    recs, _ = _records(capsys)
    assert [r["status"] for r in recs] == ["error", "ok"] and "no space left" in recs[0]["error"]
    # written to the frame's temporary (not atomically again), then renamed with the others
    assert all(atomic is False and ".part" in path.name for path, atomic in seen)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"frame_b.{s}" for s in ("S0.tiff", "DoLP.tiff", "AoP.tiff", "S0.png", "DoLP.png", "AoP.png", "polar.png",
                                 "polar.json"))


def test_record_without_the_figure_is_redone(frame, tmp_path, capsys):
    out = tmp_path / "o"
    args = ["polar", str(frame), "--out", str(out), "--png", "--json"]
    assert main(args) == 0
    _records(capsys)
    # a record as a version without the captioned figure wrote it: same options, no figure_png
    record_path = out / "frame_a.polar.json"
    rec = json.loads(record_path.read_text())
    del rec["outputs"]["figure_png"], rec["output_bytes"]["figure_png"]
    record_path.write_text(json.dumps(rec))
    (out / "frame_a.polar.png").unlink()
    assert main(args) == 0
    recs, _ = _records(capsys)
    assert not recs[0].get("resumed") and (out / "frame_a.polar.png").stat().st_size > 20_000


def test_summary_counts_processed_resumed_and_failed(frame, tmp_path, capsys):
    other = tmp_path / "in" / "frame_b.tiff"
    other.write_bytes(frame.read_bytes())
    missing = tmp_path / "in" / "missing.tiff"
    out = tmp_path / "o"
    assert main(["polar", str(frame), "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"pihim polar: 1 of 1 frames -> {out}: <stem>.S0/.DoLP/.AoP.tiff (float32, AoP in deg); "
                   "median DoLP 0.350-0.350"]
    assert main(["polar", str(frame), str(other), str(missing), "--out", str(out)]) == 2
    cap = capsys.readouterr()
    err = [ln for ln in cap.err.strip().splitlines() if ln.startswith("pihim")]  # not the progress bar
    assert cap.out == "" and len(err) == 2
    assert err[0].startswith("pihim: error:") and "missing.tiff" in err[0]
    assert err[1] == (f"pihim polar: 1 of 3 frames -> {out}: <stem>.S0/.DoLP/.AoP.tiff (float32, AoP in deg); "
                      "median DoLP 0.350-0.350; 1 of 3 already complete from an earlier run, skipped "
                      "(--overwrite redoes them); 1 failed")
    # nothing left to do: no frame processed, both skipped
    assert main(["polar", str(frame), str(other), "--out", str(out)]) == 0
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.startswith("pihim")]
    assert err == [f"pihim polar: no frame processed in {out}; 2 of 2 already complete from an earlier run, "
                   "skipped (--overwrite redoes them)"]


def test_frames_are_reported_in_input_order_when_a_later_write_finishes_first(frame, tmp_path, capsys, monkeypatch):
    """Two writer threads: the first frame's write is held until the second frame is written."""
    import threading

    import pihim.cli.polar as polar_cli

    assert polar_cli.WRITERS >= 2
    frames = []
    for k in range(3):
        p = tmp_path / "in" / f"f{k}.tiff"
        p.write_bytes(frame.read_bytes())
        frames.append(p)
    second_written = threading.Event()
    real = polar_cli.write_polar_outputs
    finished: list[str] = []

    def write(result, out_dir, stem, **kw):
        if stem == "f0":
            assert second_written.wait(10), "the second writer never ran"
        paths = real(result, out_dir, stem, **kw)
        finished.append(stem)
        if stem == "f1":
            second_written.set()
        return paths

    monkeypatch.setattr(polar_cli, "write_polar_outputs", write)
    assert main(["polar", *map(str, frames), "--out", str(tmp_path / "o"), "--json"]) == 0
    recs, _ = _records(capsys)
    assert finished[0] == "f1" and sorted(finished) == ["f0", "f1", "f2"]  # written out of order ...
    assert [r["file"] for r in recs] == [str(p) for p in frames]  # ... reported in input order
    assert all((tmp_path / "o" / f"f{k}.S0.tiff").is_file() for k in range(3))


def test_batch_previews_show_their_own_frame(tmp_path, capsys):
    """In a batch (preview arrays recycled from frame to frame) each PNG shows its own frame's images."""
    import cv2

    from pihim.visualize import aop_to_rgb, dolp_to_rgb, s0_to_gray

    frames = []
    for k, (dolp, aop) in enumerate([(0.1, 10.0), (0.6, 80.0), (0.3, 150.0), (0.8, 45.0), (0.45, 100.0)]):
        rng = np.random.default_rng(k)
        s = stokes_from_dolp_aop(rng.uniform(1500, 3000, (48, 64)), dolp, aop)
        path = tmp_path / "in" / f"f{k}.tiff"
        path.parent.mkdir(exist_ok=True)
        tifffile.imwrite(path, mosaic_from_stokes(*s, bit_depth=12, read_noise_dn=2.0, rng=k))
        frames.append(path)
    out = tmp_path / "out"
    assert main(["polar", *map(str, frames), "--out", str(out), "--png"]) == 0
    capsys.readouterr()
    for path in frames:
        s0, dolp, aop = (tifffile.imread(out / f"{path.stem}.{k}.tiff") for k in ("S0", "DoLP", "AoP"))
        shown = {k: cv2.imread(str(out / f"{path.stem}.{k}.png"), cv2.IMREAD_UNCHANGED) for k in ("S0", "DoLP", "AoP")}
        assert np.array_equal(shown["S0"], s0_to_gray(s0))
        assert np.array_equal(shown["DoLP"][..., ::-1], dolp_to_rgb(dolp))
        assert np.array_equal(shown["AoP"][..., ::-1], aop_to_rgb(aop, dolp))


def test_batch_freezes_the_collector_and_hands_it_back(frame, tmp_path, capsys, monkeypatch):
    """The long-lived objects are frozen out of the collector's passes during a batch, and unfrozen after it."""
    import gc

    before = gc.get_freeze_count()
    calls = []
    real = gc.freeze
    monkeypatch.setattr(gc, "freeze", lambda: (calls.append(1), real())[1])
    other = tmp_path / "in" / "frame_b.tiff"
    other.write_bytes(frame.read_bytes())
    assert main(["polar", str(frame), str(other), "--out", str(tmp_path / "o"), "--json"]) == 0
    capsys.readouterr()
    assert calls == [1]  # once per batch, after its first frame
    assert gc.get_freeze_count() == before  # a caller in this process keeps its collector whole


def test_png_level_changes_the_bytes_not_the_pixels(frame, tmp_path, capsys):
    """--png-level 0 (the default) stores the bare previews; 6 compresses them; the pixels are the same."""
    import cv2

    sizes, pixels = {}, {}
    for level in (0, 6):
        out = tmp_path / f"o{level}"
        assert main(["polar", str(frame), "--out", str(out), "--png", "--png-level", str(level)]) == 0
        png = out / "frame_a.DoLP.png"
        sizes[level], pixels[level] = png.stat().st_size, cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    capsys.readouterr()
    assert np.array_equal(pixels[0], pixels[6])
    assert sizes[0] > 16 * (1 + 20 * 3) > sizes[6]  # 16 x 20 RGB rows stored; a uniform DoLP compresses
    assert main(["polar", str(frame), "--out", str(tmp_path / "bad"), "--png", "--png-level", "12"]) == 2
    assert "--png-level must be a deflate level 0-9, got 12" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()  # refused before anything is written
