"""Memory budgets: refuse a request before allocating more than the machine can give.

:func:`require_memory` compares an estimate of the bytes a computation will
allocate with what the process can still obtain -- the smallest of the
kernel's ``MemAvailable``, the room left under an address-space limit
(``ulimit -v``) and the room left under a container's cgroup memory limit --
and raises :class:`~pihim.errors.PihimInputError` with
both figures when it does not fit. Estimates are deliberately generous
(temporaries included); where the available memory cannot be read, only the
absolute cap :data:`MAX_REQUEST_BYTES` applies.
"""

from __future__ import annotations

import resource

from pihim.errors import PihimInputError

#: No single request may plan on more than this, whatever the machine (1 TiB).
MAX_REQUEST_BYTES = 1 << 40


def format_bytes(n: float) -> str:
    """``1536`` -> ``'1.5 kB'``; decimal units, three significant figures.

    Examples
    --------
    >>> format_bytes(3.2e9)
    '3.2 GB'
    >>> format_bytes(512)
    '512 B'
    """
    if not n < 1e21:
        return f"{n:.3g} B"
    for unit, scale in (("EB", 1e18), ("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(n) >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n:.0f} B"


def _meminfo_available() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes, or None where unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _address_space_left() -> int | None:
    """Room under the soft ``RLIMIT_AS`` (virtual size limit), or None without a limit."""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    used = 0
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        used = 0
    return max(0, soft - used)


#: This process's cgroup memory files, (limit, usage, statistics, the reclaimable page cache's key in them):
#: cgroup v2, then v1 (a container's limit, which ``MemAvailable`` does not see).
CGROUP_MEMORY_FILES = (
    ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current", "/sys/fs/cgroup/memory.stat", "inactive_file"),
    ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes",
     "/sys/fs/cgroup/memory/memory.stat", "total_inactive_file"),
)


def _cgroup_left() -> int | None:
    """Room under the cgroup's memory limit (less its usage, the inactive page cache counted free), or None."""
    for limit_file, usage_file, stat_file, inactive_key in CGROUP_MEMORY_FILES:
        try:
            with open(limit_file, encoding="ascii") as f:
                limit = f.read().strip()
            with open(usage_file, encoding="ascii") as f:
                usage = int(f.read())
        except (OSError, ValueError):
            continue
        if limit == "max" or not limit.isdigit() or int(limit) >= 1 << 60:  # no limit (v1 writes a huge one)
            return None
        inactive = 0
        try:
            with open(stat_file, encoding="ascii") as f:
                for line in f:
                    key, _, value = line.partition(" ")
                    if key == inactive_key:
                        inactive = int(value)
                        break
        except (OSError, ValueError):
            inactive = 0
        return max(0, int(limit) - usage + inactive)
    return None


def available_memory() -> int | None:
    """Bytes this process can still allocate (best estimate), or None where it cannot be told."""
    known = [v for v in (_meminfo_available(), _address_space_left(), _cgroup_left()) if v is not None]
    return min(known) if known else None


def require_memory(nbytes: float, what: str) -> None:
    """Raise :class:`PihimInputError` unless about ``nbytes`` can be allocated now.

    Parameters
    ----------
    nbytes : float
        Estimated peak allocation of the request, bytes.
    what : str
        The request, for the message (``"--resolution 0.001 (90000 x 360000 directions)"``).

    Raises
    ------
    PihimInputError
        ``"<what> needs about 3.2 TB of memory; 6.1 GB is available"``.
    """
    try:
        nbytes = float(nbytes)
    except OverflowError:
        nbytes = float("inf")
    if not nbytes >= 0:  # also catches NaN
        raise PihimInputError(f"{what}: cannot estimate the memory it needs")
    avail = available_memory()
    limit = MAX_REQUEST_BYTES if avail is None else min(avail, MAX_REQUEST_BYTES)
    if nbytes > limit:
        have = "" if avail is None else f"; {format_bytes(avail)} is available"
        raise PihimInputError(f"{what} needs about {format_bytes(nbytes)} of memory{have}")


def memory_error_message(what: str) -> str:
    """One line for a :class:`MemoryError` that escaped the estimates."""
    avail = available_memory()
    have = "" if avail is None else f" ({format_bytes(avail)} available)"
    return f"{what}: not enough memory{have}"


__all__ = ["MAX_REQUEST_BYTES", "available_memory", "format_bytes", "memory_error_message", "require_memory"]
