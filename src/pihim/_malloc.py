"""Keep freed memory in the process for reuse (glibc's ``mallopt``), for commands that churn temporaries.

The NSTTF day sweep (``pihim windows``) allocates about 1 GB of short-lived
numpy temporaries, most of them between a few hundred kB and a few MB. glibc
returns such blocks to the system when the free space at the top of its heap
passes the trim threshold, and the next allocation takes fresh pages from the
kernel, zeroed, one page fault each: 267,000 faults and 0.6 s of system time
per sweep on the 2-core benchmark machine (8 % of its CPU time). With blocks
below 32 MB always taken from the heap and up to 256 MB of free heap kept, the
sweep takes 60 faults and 0.03 s of system time, at the same peak resident
size (202 MB against 207 MB). The whole ``pihim windows`` process, three runs
each alternated with the code before: system time 0.6-0.8 -> 0.2 s, CPU time
10.7-11.0 -> 10.3-10.7 s, peak resident size 224-238 -> 239 MB.

Only the command-line functions call this, for commands measured to gain:
the library's functions leave a process's allocator as its owner set it (a
process that runs such a command in-process, a test's ``CliRunner`` say, gets
the setting for the rest of its life). Nothing is changed where the user set
the thresholds (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, or
``glibc.malloc.mmap_threshold`` / ``glibc.malloc.trim_threshold`` in
``GLIBC_TUNABLES``) or where ``mallopt`` is not glibc's (other C libraries,
other systems).

References
----------
glibc manual, "Malloc Tunable Parameters" (``M_MMAP_THRESHOLD``,
``M_TRIM_THRESHOLD``; ``mallopt(3)``).
"""

from __future__ import annotations

import os
import sys

#: ``mallopt`` parameter numbers (glibc ``malloc.h``).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

#: Blocks this large or larger keep their own mapping (returned to the system when freed).
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: Free space at the top of the heap kept before any is returned to the system.
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024

_USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
_USER_TUNABLES = ("glibc.malloc.mmap_threshold", "glibc.malloc.trim_threshold")


def _user_set() -> bool:
    """Whether the user set either threshold in the environment."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    return any(os.environ.get(k) for k in _USER_SETTINGS) or any(t in tunables for t in _USER_TUNABLES)


def keep_freed_memory(mmap_threshold: int = MMAP_THRESHOLD_BYTES, trim_threshold: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Set glibc's mmap and trim thresholds for this process; True if both were set.

    Parameters
    ----------
    mmap_threshold : int
        Bytes from which an allocation gets its own mapping (glibc's default
        starts at 128 kB and follows the largest block freed, up to 32 MB).
    trim_threshold : int
        Free bytes at the top of the heap kept before trimming (glibc's
        default follows the mmap threshold: twice it).

    Returns
    -------
    bool
        False when not both were set: not Linux, the user set either
        threshold in the environment (then nothing is changed), or the C
        library has no ``mallopt`` that accepted them.

    Raises
    ------
    ValueError
        A threshold outside ``[0, 2**31)`` (``mallopt`` takes a C ``int``).
    """
    for name, value in (("mmap_threshold", mmap_threshold), ("trim_threshold", trim_threshold)):
        if not 0 <= int(value) < 2**31:
            raise ValueError(f"{name} must be in [0, 2**31), got {value!r}")
    if not sys.platform.startswith("linux") or _user_set():
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success, 0 on an error (musl's stub always 0)
    return bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(M_TRIM_THRESHOLD, int(trim_threshold)))
