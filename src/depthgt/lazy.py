"""A package whose names load on first use (PEP 562), so that a torch-free module inside it
(its ``settings``) can be imported without importing torch.

The package writes its names as ordinary imports under ``if TYPE_CHECKING:`` (what type
checkers, readers and ``tests/test_layers.py`` see) and ends with
``__getattr__, __dir__ = lazy_names(__name__, __file__)``: the first use of a name imports
its module. A name that is also a submodule's (``depthgt.registration.align``: the
function and its module) stays the name when the submodule is imported directly.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
import types
from collections.abc import Callable
from pathlib import Path

__all__ = ["lazy_names"]


def _type_checking_imports(path: str, package: str) -> dict[str, tuple[str, str]]:
    """Name -> (module, attribute) of every ``from ... import`` under ``if TYPE_CHECKING:``."""
    names: dict[str, tuple[str, str]] = {}
    for node in ast.parse(Path(path).read_text(), filename=path).body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for imp in node.body:
                if isinstance(imp, ast.ImportFrom):
                    module = "." * imp.level + (imp.module or "")
                    module = importlib.util.resolve_name(module, package) if imp.level else module
                    names.update({a.asname or a.name: (module, a.name) for a in imp.names})
    return names


class _Package(types.ModuleType):
    """The import system sets a package's attribute to a submodule once it has loaded it;
    a name the package exports keeps its value (``registration.align`` stays the function)."""

    def __setattr__(self, name: str, value) -> None:
        source = self.__dict__.get("_lazy_names", {}).get(name)
        if isinstance(value, types.ModuleType) and source is not None and source[0] != self.__name__:
            value = getattr(importlib.import_module(source[0]), source[1])
        super().__setattr__(name, value)


def lazy_names(package: str, path: str) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` of the package ``package`` (its ``__init__.py`` at
    ``path``): each name of its ``TYPE_CHECKING`` imports is imported on first use."""
    names = _type_checking_imports(path, package)
    module = sys.modules[package]
    module._lazy_names = names
    module.__class__ = _Package

    def __getattr__(name: str):
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        source, attr = names[name]
        value = getattr(importlib.import_module(source), attr)
        setattr(module, name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*module.__dict__, *names})

    return __getattr__, __dir__
