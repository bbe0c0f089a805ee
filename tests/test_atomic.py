"""Atomic writes, writer-named temporaries and the cleaning of stale ones (``pihim._atomic``)."""

import os
import stat
import subprocess
import sys
import time

import pytest

from pihim._atomic import (
    LEGACY_TEMP_MAX_AGE_S,
    _host_tag,
    atomic_group,
    check_out_dir,
    clean_stale_temporaries,
    output_dir,
    output_target,
    temp_sibling,
    write_group,
    write_text_atomic,
)
from pihim.errors import PihimInputError


def _dead_pid() -> int:
    """The id of a process that has exited."""
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def test_temp_sibling_names_its_writer(tmp_path):
    tmp = temp_sibling(tmp_path / "a.S0.tiff")
    assert tmp.parent == tmp_path and tmp.suffix == ".tiff"
    assert tmp.name.startswith(f".a.S0.pihim-{_host_tag()}-{os.getpid()}-") and ".part" in tmp.name
    assert clean_stale_temporaries(tmp_path) == []  # this process is alive: its temporary stays
    assert tmp.exists()


def test_clean_removes_only_temporaries_of_gone_processes(tmp_path):
    pid = _dead_pid()
    stale = tmp_path / f".x.pihim-{_host_tag()}-{pid}-abcdefgh.part.tiff"
    other_host = tmp_path / f".x.pihim-{'0000' if _host_tag() != '0000' else '1111'}-{pid}-abcdefgh.part.tiff"
    legacy_old = tmp_path / ".y.k2j4h5g6.part.png"
    legacy_new = tmp_path / ".z.k2j4h5g6.part.png"
    ordinary = tmp_path / "x.tiff"
    for p in (stale, other_host, legacy_old, legacy_new, ordinary):
        p.write_bytes(b"data")
    old = time.time() - LEGACY_TEMP_MAX_AGE_S - 60
    os.utime(legacy_old, (old, old))
    removed = clean_stale_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == sorted([stale.name, legacy_old.name])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([other_host.name, legacy_new.name, ordinary.name])


def test_atomic_group_all_or_nothing(tmp_path):
    finals = [tmp_path / "a.txt", tmp_path / "b.txt"]
    with pytest.raises(RuntimeError):
        with atomic_group(finals) as tmps:
            tmps[0].write_text("a")
            raise RuntimeError("second file failed")
    assert list(tmp_path.iterdir()) == []
    with atomic_group(finals) as tmps:
        for t, text in zip(tmps, "ab", strict=True):
            t.write_text(text)
    assert [p.read_text() for p in finals] == ["a", "b"] and len(list(tmp_path.iterdir())) == 2


def test_write_group_runs_every_writer_before_any_rename(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.png"

    def fail(path):
        path.write_bytes(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError):
        write_group({a: lambda p: p.write_text("{}"), b: fail})
    assert list(tmp_path.iterdir()) == []
    assert write_group({a: lambda p: p.write_text("{}"), b: lambda p: p.write_bytes(b"png")}) == [a, b]
    assert a.read_text() == "{}" and b.read_bytes() == b"png" and len(list(tmp_path.iterdir())) == 2


def test_output_dir_removes_the_folders_it_made_when_the_run_fails(tmp_path):
    out = tmp_path / "a" / "b" / "out"
    with pytest.raises(KeyboardInterrupt):
        with output_dir(out) as p:
            assert p == out and out.is_dir()
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []  # out and the parents made for it
    with output_dir(out) as p:  # success: kept, even empty
        pass
    assert out.is_dir()


def test_output_dir_keeps_a_folder_that_was_there_or_holds_anything(tmp_path):
    there = tmp_path / "there"
    there.mkdir()
    with pytest.raises(OSError):
        with output_dir(there):
            raise OSError(28, "No space left on device")
    assert there.is_dir()
    made = tmp_path / "p" / "made"
    with pytest.raises(RuntimeError):
        with output_dir(made):
            (made / "first.json").write_text("{}")  # a finished result of a batch is never removed
            raise RuntimeError("second item failed")
    assert (made / "first.json").read_text() == "{}"


def test_an_out_folder_on_a_read_only_file_system_is_named_so(tmp_path, monkeypatch):
    """Not "permission denied" (root gets that message on a read-only mount too, where chmod would not help)."""
    from types import SimpleNamespace

    from pihim.errors import PihimInputError

    monkeypatch.setattr(os, "access", lambda *a, **k: False)
    flags = {"f_flag": os.ST_RDONLY}
    monkeypatch.setattr(os, "statvfs", lambda p: SimpleNamespace(**flags))
    with pytest.raises(PihimInputError, match=r"cannot write in .* \(a read-only file system\)"):
        check_out_dir(tmp_path / "out")
    flags["f_flag"] = 0
    with pytest.raises(PihimInputError, match=r"cannot write in .* \(permission denied\)"):
        check_out_dir(tmp_path / "out")


def test_outputs_never_replace_a_device_or_a_pipe(tmp_path):
    """Renaming onto /dev/null or a FIFO would turn it into a regular file holding the output: refused."""
    with pytest.raises(PihimInputError, match=r"^--out /dev/null: is a character device, not a regular file"):
        output_target("/dev/null", option="--out")
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    with pytest.raises(PihimInputError, match="pipe.json: is a named pipe"):
        write_text_atomic(fifo, "{}")
    with pytest.raises(PihimInputError, match="is a named pipe"), atomic_group([tmp_path / "a.json", fifo]):
        raise AssertionError("not reached")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe.json"]  # no temporary, nothing else written
    with pytest.raises(PihimInputError, match="is a directory"):
        output_target(tmp_path)


def test_outputs_follow_a_link_and_keep_it(tmp_path):
    """A symbolic link to a file is followed: the file it names gets the output, the link stays a link."""
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "out.json"
    target.write_text("old")
    link = tmp_path / "out.json"
    link.symlink_to(target)
    write_text_atomic(link, "new")
    assert link.is_symlink() and target.read_text() == "new"
    dangling = tmp_path / "later.json"
    dangling.symlink_to(tmp_path / "real" / "later.json")
    with atomic_group([dangling]) as (tmp,):
        tmp.write_text("made")
    assert dangling.is_symlink() and (tmp_path / "real" / "later.json").read_text() == "made"
    fifo = tmp_path / "real" / "fifo"
    os.mkfifo(fifo)
    to_fifo = tmp_path / "to_fifo"
    to_fifo.symlink_to(fifo)
    with pytest.raises(PihimInputError, match=r"to_fifo: is a named pipe \(through the link, .*fifo\)"):
        write_text_atomic(to_fifo, "x")
