"""
The package's one import of Open3D, without the subpackages it never uses.

Open3D's ``__init__`` imports ``open3d.ml`` (whose datasets import scikit-learn, pandas and
scipy.stats) and ``open3d.visualization`` (whose plotly viewer imports dash): most of the
import's time, paid by every process that runs the front end (the node's registration
processes, each CLI, the tests that start them; docs/lifecycle.md). While ``import open3d``
runs, both are placeholders in ``sys.modules``; afterwards each stays on the package as a
stand-in that imports the real subpackage at its first attribute, and ``import open3d.ml``
imports it as usual: whoever uses them still gets Open3D's own. A placeholder touched during
the import imports the real subpackage there and then, as Open3D's own line would have; an
import that fails with the placeholders is done again plainly. Open3D imported before this
module is used as it is.
"""

from __future__ import annotations

import importlib
from pathlib import Path
import sys
import types
from typing import Any, Sequence

# Open3D's subpackages that the package never uses, left to their first use.
DEFERRED = ('ml', 'visualization')


class DeferredModule(types.ModuleType):
    """A subpackage not imported yet: an attribute it lacks imports it, and is the real one's."""

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.resolve(), attr)

    def __dir__(self) -> list[str]:
        return dir(self.resolve())

    def __repr__(self) -> str:
        return f'<deferred module {self.__name__!r}>'

    def resolve(self) -> types.ModuleType:
        """Import the real subpackage (once; the import sets it on its parent)."""
        name = self.__name__
        if sys.modules.get(name) is self:
            del sys.modules[name]
        return importlib.import_module(name)


def import_deferring(name: str, deferred: Sequence[str]) -> types.ModuleType:
    """
    Import the package ``name`` with its subpackages ``deferred`` left to their first use.

    :return: the package, as ``import name`` gives it; a package already imported is returned
        as it is.
    """
    if name in sys.modules:
        return sys.modules[name]
    placeholders = {sub: DeferredModule(f'{name}.{sub}') for sub in deferred
                    if f'{name}.{sub}' not in sys.modules}
    before = set(sys.modules)
    sys.modules.update({p.__name__: p for p in placeholders.values()})
    try:
        package = importlib.import_module(name)
    except Exception:
        for p in placeholders.values():
            if sys.modules.get(p.__name__) is p:
                del sys.modules[p.__name__]
        return _import_again(name)
    for sub, p in placeholders.items():
        if sys.modules.get(p.__name__) is not p:
            continue  # imported for real while the package was
        del sys.modules[p.__name__]
        _drop_hiding_aliases(package, sub, before)
        if getattr(package, sub, p) is p:
            setattr(package, sub, p)
    return package


def _import_again(name: str) -> types.ModuleType:
    """
    Import ``name`` plainly after an attempt that failed, as if it were the first.

    The submodules the failed attempt imported stay in ``sys.modules`` (a compiled one cannot
    be loaded twice), so the second import does not set them on the new package: set them.
    """
    package = importlib.import_module(name)
    prefix = f'{name}.'
    for key, module in list(sys.modules.items()):
        attr = key[len(prefix):]
        if (key.startswith(prefix) and '.' not in attr and getattr(module, '__name__', '') == key
                and not hasattr(package, attr)):
            setattr(package, attr, module)
    return package


def _drop_hiding_aliases(package: types.ModuleType, sub: str, before: set[str]) -> None:
    """
    Forget names the import gave under a deferred subpackage that hide its Python modules.

    Open3D names its compiled submodules under the Python ones (``open3d.ml.contrib`` for
    ``open3d.cpu.pybind.ml.contrib``) where no Python module of that name was imported first;
    the subpackage imported later must find its own modules, as after a plain import.
    """
    prefix = f'{package.__name__}.{sub}.'
    roots = [Path(p) / sub for p in getattr(package, '__path__', ())]
    for key in [k for k in sys.modules if k.startswith(prefix) and k not in before]:
        if getattr(sys.modules[key], '__name__', key) == key:
            continue
        parts = key[len(prefix):].split('.')
        if any(root.joinpath(*parts).with_suffix('.py').is_file()
               or root.joinpath(*parts, '__init__.py').is_file() for root in roots):
            del sys.modules[key]


open3d = import_deferring('open3d', DEFERRED)
