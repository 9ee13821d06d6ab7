"""Lazy public names for a package: resolved from their owning module on first use, so importing the
package loads no heavy dependency (torch, Warp) until a name is asked for."""

from __future__ import annotations

import importlib


def lazy_exports(package: str, namespace: dict, exports: dict[str, str]):
    """(__getattr__, __dir__) for `package`, whose module globals are `namespace`, serving
    `exports` (public name -> owning module)."""
    public = sorted(set(namespace.get("__all__", ())) | set(exports))

    def __getattr__(name: str):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    def __dir__():
        return public

    return __getattr__, __dir__
