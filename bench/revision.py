"""
The registration core of an earlier git revision, imported beside the working tree's.

``git archive`` writes the package of that revision into a folder, renamed ``cgags_prev``
(every ``cgags_ros`` in its sources too), and it is imported from there under that name,
so both cores run in one process on the same problems (``bench.ab_core``, the
``ours-4dof@REV`` solvers of ``bench.core``). Its NamedTuple classes are renamed too
(``Correspondences`` -> ``CorrespondencesPrev``): numba's dispatcher tells a NamedTuple
argument's type by its class's name and fields, so a call into the second core with its
own ``Correspondences`` would be typed as the first core's class and refused.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
from pathlib import Path
import re
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = 'cgags_prev'
NAMED_TUPLE = re.compile(r'^class (\w+)\((?:typing\.)?NamedTuple\)', re.M)


def load_previous(rev: str, where: Path):
    """Return ``register_correspondences`` of the package at git ``rev``, as cgags_prev."""
    archive = subprocess.run(['git', '-C', str(ROOT), 'archive', rev, 'cgags_ros'],
                             check=True, capture_output=True).stdout
    subprocess.run(['tar', '-x', '-C', str(where)], input=archive, check=True)
    package = where / PACKAGE
    (where / 'cgags_ros').rename(package)
    sources = {path: path.read_text(encoding='utf-8').replace('cgags_ros', PACKAGE)
               for path in package.rglob('*.py')}
    names = sorted({name for text in sources.values() for name in NAMED_TUPLE.findall(text)})
    for path, text in sources.items():
        if names:
            text = re.sub(r'\b(' + '|'.join(names) + r')\b', r'\1Prev', text)
        path.write_text(text, encoding='utf-8')
    spec = importlib.util.spec_from_file_location(
        PACKAGE, package / '__init__.py', submodule_search_locations=[str(package)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[PACKAGE] = module
    spec.loader.exec_module(module)
    return importlib.import_module(f'{PACKAGE}.registration').register_correspondences


def previous_config(cfg):
    """Return the previous revision's CoreConfig with ``cfg``'s values (its own defaults else)."""
    previous = sys.modules[f'{PACKAGE}.registration'].CoreConfig
    return previous(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(previous)
                       if hasattr(cfg, f.name)})
