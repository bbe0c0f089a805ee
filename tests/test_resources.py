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
