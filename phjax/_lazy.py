"""Lazy re-exports (PEP 562): a package names its public API at the top without importing the
heavy parts (optimistix, OpenCV, the live and vision layers) until first used, so that
``import phjax`` costs little more than ``import jax`` and ``equinox``."""

from __future__ import annotations

import importlib

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: dict[str, tuple[str, ...]]):
    """``(__getattr__, __dir__)`` for a package whose names ``exports[module]`` live in
    ``package.module`` (``""`` for the module itself, a subpackage) and are imported on first
    access.

    Arguments:
        package: the package's ``__name__``.
        exports: relative module name -> names it provides.

    Returns:
        The two module-level functions; assign them in the package's ``__init__``.
    """
    where = {name: module for module, names in exports.items() for name in names}
    for module in exports:
        if module and "." not in module:
            where.setdefault(module, module)  # the submodule itself

    def __getattr__(name: str):
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        mod = importlib.import_module(f"{package}.{module}")
        value = mod if name == module else getattr(mod, name)
        globals_ = importlib.import_module(package).__dict__
        globals_[name] = value  # later accesses skip __getattr__
        return value

    def __dir__():
        return sorted(set(importlib.import_module(package).__dict__) | set(where))

    return __getattr__, __dir__
