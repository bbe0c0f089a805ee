"""Atomic file output: write to a temporary sibling, then rename.

A crash or a failed write therefore never leaves a half-written file under
the final name. A process killed outright (SIGKILL, power loss) cannot remove
its temporary files; their names therefore carry the writing process's host
and id (``.NAME.pihim-HHHH-PID-XXXXXXXX.part.EXT``) so that a later run can
tell them from the temporaries of a run still going and remove them
(:func:`clean_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import socket
import stat
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from pihim.errors import PihimInputError

_UMASK = os.umask(0)
os.umask(_UMASK)

#: Temporary names written by this module: ``.STEM.pihim-HOST-PID-RANDOM.partSUFFIX``.
_TEMP_RE = re.compile(r"^\..+\.pihim-(?P<host>[0-9a-f]{4})-(?P<pid>\d+)-[a-z0-9_]{8}\.part(\.[^/]*)?$")
#: Temporaries of the older ``mkstemp`` naming (``.STEM.RANDOM.partSUFFIX``, no owner recorded).
_LEGACY_TEMP_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.part(\.[^/]*)?$")
#: A legacy temporary older than this (seconds) belongs to no running writer.
LEGACY_TEMP_MAX_AGE_S = 3600.0


def _host_tag() -> str:
    """Four hex digits identifying this host (temporaries of other hosts are never removed)."""
    return hashlib.sha1(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:4]


def temp_sibling(path: str | os.PathLike[str], register: list[Path] | None = None) -> Path:
    """Create an empty temporary file next to ``path`` and return its path.

    The name keeps the final suffix, so writers that dispatch on the
    extension (OpenCV, tifffile) behave as for the final name, and records
    the host and process id of the writer. The file gets the permissions of
    an ordinary new file (``0666 & ~umask``). With ``register``, the path is
    appended to it before anything else can happen, so that a caller cleaning
    up after an interruption (SIGTERM raises in the main thread) knows every
    temporary it made; an interruption inside this function removes the file.
    """
    final = Path(path)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{final.stem}.pihim-{_host_tag()}-{os.getpid()}-", suffix=f".part{final.suffix}", dir=final.parent
    )
    try:
        os.close(fd)
        if register is not None:
            register.append(Path(tmp_name))
        os.chmod(tmp_name, 0o666 & ~_UMASK)  # mkstemp creates 0600; give outputs the usual permissions
    except BaseException:
        if register is None or Path(tmp_name) not in register:
            with contextlib.suppress(OSError):
                os.unlink(tmp_name)
        raise
    return Path(tmp_name)


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # exists but belongs to someone else, or cannot tell: keep its files
    return True


def is_stale_temporary(entry: os.DirEntry[str] | Path, *, now: float | None = None) -> bool:
    """Whether ``entry`` is a temporary file of :func:`temp_sibling` whose writer is gone.

    A temporary of this host whose process no longer exists is stale; one of
    another host never is (its process cannot be checked). A temporary of the
    older naming, which records no process, is stale once older than
    :data:`LEGACY_TEMP_MAX_AGE_S`.
    """
    name = entry.name
    m = _TEMP_RE.match(name)
    if m is not None:
        return m["host"] == _host_tag() and not _pid_alive(int(m["pid"]))
    if _LEGACY_TEMP_RE.match(name) is not None:
        try:
            age = (time.time() if now is None else now) - os.stat(entry, follow_symlinks=False).st_mtime
        except OSError:
            return False
        return age > LEGACY_TEMP_MAX_AGE_S
    return False


def clean_stale_temporaries_tree(directory: str | os.PathLike[str], *, depth: int = 2) -> list[Path]:
    """:func:`clean_stale_temporaries` in ``directory`` and its sub-folders down to ``depth`` levels.

    For commands that write a tree of outputs (``pihim demo``: ``DIR``,
    ``DIR/plan``, ``DIR/pairs/NN_*``). Symbolic links to folders are not followed.
    """
    removed = clean_stale_temporaries(directory)
    if depth <= 0:
        return removed
    try:
        subdirs = [e.path for e in os.scandir(directory) if e.is_dir(follow_symlinks=False)]
    except OSError:
        return removed
    for sub in sorted(subdirs):
        removed += clean_stale_temporaries_tree(sub, depth=depth - 1)
    return removed


#: numpy's ``tofile`` (behind tifffile) reports a full disk without an errno, as "N requested and M written".
_SHORT_WRITE_RE = re.compile(r"(\d+) requested and (\d+) written")


def describe_os_error(exc: OSError) -> str:
    """One line for an operating-system error while writing, naming a full disk as such.

    >>> describe_os_error(OSError("1253376 requested and 749500 written"))
    'no space left on the device (1253376 bytes requested, 749500 written)'
    >>> describe_os_error(OSError(13, "Permission denied"))
    'Permission denied'
    """
    import errno

    text = " ".join(str(exc).split())
    m = _SHORT_WRITE_RE.search(text)
    if m is not None:
        return f"no space left on the device ({m[1]} bytes requested, {m[2]} written)"
    if exc.errno == errno.ENOSPC:
        return "no space left on the device"
    return " ".join((exc.strerror or text or type(exc).__name__).split())


def clean_stale_temporaries(directory: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporaries that killed runs left in ``directory`` (not recursive).

    Returns the removed paths. Files that cannot be listed or removed are
    left alone: cleaning never fails a run.
    """
    removed: list[Path] = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    for entry in entries:
        try:
            if not entry.is_file(follow_symlinks=False) or not is_stale_temporary(entry):
                continue
            os.unlink(entry.path)
        except OSError:
            continue
        removed.append(Path(entry.path))
    return removed


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, in words (``stat`` mode bits)."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def output_target(path: str | os.PathLike[str], *, option: str | None = None) -> Path:
    """The file an output written to ``path`` replaces: ``path``, or the file its symbolic link points to.

    Renaming a finished temporary onto ``path`` replaces whatever is there: a
    device such as ``/dev/null`` or a named pipe would silently become a
    regular file holding the output, and a symbolic link would be replaced
    by the file instead of the file it names being updated. So a link is
    followed (the output goes where it points, the link stays), and a path
    that is, or leads to, anything but a regular file or nothing is refused.

    Raises
    ------
    PihimInputError
        ``path`` exists and is not a regular file (after following links);
        the message starts with ``option`` (e.g. ``--out``) when given.
    """
    p = Path(path)
    if p.is_symlink():
        p = Path(os.path.realpath(p))
    try:
        mode = os.stat(p).st_mode
    except OSError:  # nothing there yet (or it cannot be looked at: the write reports it)
        return p
    if stat.S_ISREG(mode):
        return p
    label = os.fspath(path) if option is None else f"{option} {os.fspath(path)}"
    shown = "" if p == Path(path) else f" (through the link, {p})"
    raise PihimInputError(f"{label}: is {_kind(mode)}{shown}, not a regular file; pihim writes its outputs only to "
                          "regular files (give another file name)")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    A symbolic link at ``path`` is followed, and anything but a regular file
    there is refused (:func:`output_target`).
    """
    final = output_target(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    made: list[Path] = []
    try:
        temp_sibling(final, made)
        yield made[0]
        os.replace(made[0], final)
    except BaseException:
        for tmp in made:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_group(paths: Sequence[str | os.PathLike[str]]) -> Iterator[list[Path]]:
    """Yield one temporary path per entry of ``paths``; rename them all when the block succeeds.

    Every file is written in full before the first rename, so the final
    names appear within a few renames of each other; on any failure the
    temporaries and any file already renamed are removed. (A kill between two
    renames can still leave part of the group: mark completion with a file
    written after the group when that matters.) Each entry is checked, and
    a link followed, as in :func:`atomic_path`.
    """
    finals = [output_target(p) for p in paths]
    tmps: list[Path] = []
    done: list[Path] = []
    try:
        for final in finals:
            final.parent.mkdir(parents=True, exist_ok=True)
            temp_sibling(final, tmps)
        yield list(tmps)
        for tmp, final in zip(tmps, finals, strict=True):
            os.replace(tmp, final)
            done.append(final)
    except BaseException:
        for p in [*tmps, *done]:
            with contextlib.suppress(OSError):
                p.unlink()
        raise


def write_group(writers: Mapping[str | os.PathLike[str], Callable[[Path], Any]]) -> list[Path]:
    """Write a group of files with :func:`atomic_group`: ``writers`` maps each final path to ``f(temp_path)``.

    Every writer runs on its temporary path first; the renames follow only
    when all succeeded, and on any failure nothing of the group is left.
    """
    finals = [Path(p) for p in writers]
    with atomic_group(finals) as tmps:
        for tmp, writer in zip(tmps, writers.values(), strict=True):
            writer(tmp)
    return finals


def write_atomic(path: str | os.PathLike[str], writer: Callable[[Path], Any]) -> Path:
    """Call ``writer(tmp_path)`` and atomically move the result to ``path``."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return write_atomic(path, lambda p: p.write_text(text, encoding="utf-8"))


def write_json_atomic(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    return write_text_atomic(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


# -- output folders --------------------------------------------------------------------------------


def check_not_an_input(out: str | os.PathLike, inputs: Iterable[str | os.PathLike], *, option: str = "--out") -> None:
    """Refuse an output file that is one of the inputs: writing it would replace that input.

    Compared as files (:func:`os.path.samefile`), so another spelling of the path or a link is caught too.
    """
    p = Path(out)
    if not p.exists():
        return
    for q in inputs:
        try:
            same = os.path.samefile(p, q)
        except OSError:  # an input that cannot be looked at is reported when it is read
            continue
        if same:
            raise PihimInputError(f"{option} {out}: is the input {os.fspath(q)}; writing it would replace that input")


def missing_dirs(out: str | os.PathLike) -> list[Path]:
    """The directories that making ``out`` (with its parents) would create, deepest first (absolute paths)."""
    missing: list[Path] = []
    for q in (Path(out).absolute(), *Path(out).absolute().parents):
        if q.exists():
            break
        missing.append(q)
    return missing


def remove_empty_dirs(dirs: Iterable[Path]) -> None:
    """Remove those of ``dirs`` (deepest first) that are empty: an output folder a run made and left unused."""
    for q in dirs:
        with contextlib.suppress(OSError):
            q.rmdir()


def check_out_dir(out: str | os.PathLike, *, option: str = "--out") -> None:
    """Refuse an output directory that cannot be one, before any work is done.

    ``out`` must be a directory or not exist yet; its nearest existing
    ancestor must be a writable directory; and a missing ``out`` must be
    creatable: it is created and removed again at once (so that, say,
    ``--out /proc/x`` is refused before a long computation, not after it);
    an existing ``out`` must take a file (one is created and removed: the
    permission bits do not tell, e.g. for root under ``/sys``). Nothing is
    left behind (see :func:`make_out_dir`).
    """
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise PihimInputError(f"{option} {out}: exists and is not a directory")
    missing = missing_dirs(p)
    existing = missing[-1].parent if missing else p.absolute()  # the nearest ancestor there is
    if not existing.is_dir():
        raise PihimInputError(f"{option} {out}: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        why = "permission denied"
        with contextlib.suppress(OSError, AttributeError):
            if os.statvfs(existing).f_flag & os.ST_RDONLY:
                why = "a read-only file system"
        raise PihimInputError(f"{option} {out}: cannot write in {existing} ({why})")
    if not missing:
        try:  # access() answers from the mode bits: as root, /sys or a read-only mount looked writable
            probe = temp_sibling(p / "write-probe")  # named as a temporary: a killed run's is cleaned later
        except OSError as exc:
            raise PihimInputError(f"{option} {out}: cannot write in {p} ({describe_os_error(exc)})") from None
        with contextlib.suppress(OSError):
            probe.unlink()
        return
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PihimInputError(f"{option} {out}: cannot create the directory ({exc.strerror or exc})") from None
    finally:
        remove_empty_dirs(missing)  # a folder another process filled meanwhile is not empty and stays


def make_out_dir(out: str | os.PathLike, *, option: str = "--out") -> Path:
    """Create the output directory (one-line error if impossible) and clean stale temporaries in it.

    Temporary files that killed runs left behind (see
    :func:`clean_stale_temporaries`) are removed. ``option`` names the
    directory in error messages (the command's option, or a parameter name).
    """
    p = Path(out)
    check_out_dir(p, option=option)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PihimInputError(f"{option} {out}: cannot create the directory ({exc.strerror or exc})") from None
    clean_stale_temporaries(p)
    return p


@contextlib.contextmanager
def output_dir(out: str | os.PathLike, *, option: str = "--out") -> Iterator[Path]:
    """:func:`make_out_dir` for one run's outputs; if the block fails, the folders made for it go again.

    A run refused, interrupted (Ctrl-C, SIGTERM) or failing before its first
    file is in place leaves no empty ``out`` (nor the parents made for it)
    behind. Only folders this call created are removed, and only while empty:
    a folder that was there before, or that holds anything, stays.
    """
    made = missing_dirs(out)
    p = make_out_dir(out, option=option)
    try:
        yield p
    except BaseException:
        remove_empty_dirs(made)
        raise
