"""Lazy package namespaces: a package lists what it exports, submodules load on first use.

``import pihim.camera`` then costs nothing beyond the package itself; the
numba kernels behind ``pihim.camera.polar_image``, for instance, are imported
only when ``polar_image`` is first looked up. This keeps every command-line
start-up quick (only what a command uses is imported) without changing the
public names (PEP 562 module ``__getattr__``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any


def lazy_exports(
    package: str, exports: Mapping[str, Sequence[str]]
) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
    """``__getattr__``, ``__dir__`` and ``__all__`` of a package that exports names of its submodules lazily.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : mapping
        Submodule name (relative, e.g. ``"pipeline"``) -> the names it provides to the package.

    Returns
    -------
    getattr, dir : callable
        To assign to the package's ``__getattr__`` and ``__dir__``.
    all : list of str
        The exported names, sorted, for ``__all__``.

    Examples
    --------
    In ``pihim/camera/__init__.py``::

        __getattr__, __dir__, __all__ = lazy_exports(__name__, {"pipeline": ["polar_image"]})
    """
    where = {name: sub for sub, names in exports.items() for name in names}
    module = importlib.import_module(package)

    def __getattr__(name: str) -> Any:
        sub = where.get(name)
        if sub is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{sub}"), name)
        setattr(module, name, value)  # later lookups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(module)) | set(where))

    return __getattr__, __dir__, sorted(where)
