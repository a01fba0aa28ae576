"""A package's public names, imported the first time one is asked for (PEP 562), as scipy loads its own.

A package lists its API as {name: module that defines it}; `import flockcal` then costs no numpy, and
`flockcal --help` loads nothing the command line does not run. `dir()` and `__all__` list the names.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping


def public_api(package: str, table: Mapping[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]], list[str]]:
    """(`__getattr__`, `__dir__`, `__all__`) for `package`, whose public names are `table`'s keys, each
    defined in the module its value names.

    A name spelled like the submodule that defines it (`flockcal.solver.solve`, the function in
    solver/solve.py) is imported now: importing that submodule sets the package's attribute to the
    module, and a module-level `__getattr__` is only asked for names the package does not have.
    """
    def __getattr__(name: str):
        if name not in table:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(table[name]), name)
        setattr(sys.modules[package], name, value)  # asked once: later lookups find it as a plain attribute
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(table))

    for name, module in table.items():
        if module.rsplit(".", 1)[-1] == name:
            __getattr__(name)
    return __getattr__, __dir__, list(table)
