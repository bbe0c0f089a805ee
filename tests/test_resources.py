"""Memory budgets (``pihim._resources``)."""

import pytest

import pihim._resources as resources
from pihim.errors import PihimInputError


def test_format_bytes():
    assert resources.format_bytes(512) == "512 B"
    assert resources.format_bytes(123_000) == "123 kB"
    assert resources.format_bytes(3.2e9) == "3.2 GB"
    assert resources.format_bytes(1e15) == "1 PB"


def test_require_memory_refuses_with_both_figures(monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: 2_000_000_000)
    resources.require_memory(1_000_000_000, "small request")
    with pytest.raises(PihimInputError) as err:
        resources.require_memory(3.5e9, "--thing 7")
    assert str(err.value) == "--thing 7 needs about 3.5 GB of memory; 2 GB is available"
    with pytest.raises(PihimInputError, match="needs about"):
        resources.require_memory(10**400, "--huge")  # beyond float range


def test_absolute_cap_without_a_reading(monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: None)
    resources.require_memory(1e9, "ok")
    with pytest.raises(PihimInputError, match="needs about 2 TB of memory$"):
        resources.require_memory(2e12, "x")


def test_available_memory_sees_the_address_space_limit():
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    try:
        resource.setrlimit(resource.RLIMIT_AS, (resource.RLIM_INFINITY, hard))
        unlimited = resources.available_memory()
        limit = 64 << 40  # 64 TiB: above any current use, below MemAvailable only on huge machines
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
        left = resources._address_space_left()
        assert left is not None and 0 < left < limit
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    assert unlimited is None or unlimited > 0


def test_available_memory_sees_a_cgroup_limit(tmp_path, monkeypatch):
    """A container's limit (cgroup v2, then v1) less its usage, the inactive page cache counted free."""
    from pihim import _resources

    def files(limit, usage, stat, key="inactive_file"):
        d = tmp_path / f"cg{len(list(tmp_path.iterdir()))}"
        d.mkdir()
        (d / "max").write_text(limit + "\n")
        (d / "current").write_text(f"{usage}\n")
        (d / "stat").write_text(stat)
        return (str(d / "max"), str(d / "current"), str(d / "stat"), key)

    v2 = files("1000000000", 600_000_000, "anon 400000000\ninactive_file 100000000\nactive_file 5\n")
    monkeypatch.setattr(_resources, "CGROUP_MEMORY_FILES", (v2,))
    assert _resources._cgroup_left() == 500_000_000
    monkeypatch.setattr(_resources, "_meminfo_available", lambda: 10**12)
    assert _resources.available_memory() == 500_000_000  # the smallest figure wins
    monkeypatch.setattr(_resources, "CGROUP_MEMORY_FILES", (files("max", 5, ""),))
    assert _resources._cgroup_left() is None  # no limit
    missing = (str(tmp_path / "nope"), str(tmp_path / "nope2"), str(tmp_path / "nope3"), "x")
    v1 = files(str(2**63 - 4096), 5, "total_inactive_file 3\n", "total_inactive_file")
    monkeypatch.setattr(_resources, "CGROUP_MEMORY_FILES", (missing, v1))
    assert _resources._cgroup_left() is None  # v1's "no limit" is a huge number
    v1 = files("2000", 1500, "total_inactive_file 300\n", "total_inactive_file")
    monkeypatch.setattr(_resources, "CGROUP_MEMORY_FILES", (missing, v1))
    assert _resources._cgroup_left() == 800
