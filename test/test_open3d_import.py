"""
cgags_ros.open3d_import: Open3D without its unused subpackages, and nothing else changed.

Small stand-in packages show each path (deferred, used during the import, a failed attempt
done again, compiled aliases); Open3D itself, in fresh processes, shows that once its
subpackages are imported everything in ``sys.modules`` is what a plain ``import open3d`` gives.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
import subprocess
import sys
import textwrap

from cgags_ros.open3d_import import DeferredModule, import_deferring
import pytest

ROOT = Path(__file__).resolve().parents[1]
NAME = 'cgags_fake3d'  # a package name no one else uses


@pytest.fixture
def fake(tmp_path, monkeypatch):
    """Write a stand-in package (``__init__`` body given) and forget it afterwards."""
    monkeypatch.syspath_prepend(str(tmp_path))

    def write(init: str, files: dict[str, str] | None = None) -> Path:
        root = tmp_path / NAME
        for rel, text in {'__init__.py': init, 'ml/__init__.py': 'VALUE = 42\n',
                          'viz/__init__.py': 'SHOWN = True\n', **(files or {})}.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text(textwrap.dedent(init if rel == '__init__.py' else text))
        importlib.invalidate_caches()
        return root

    yield write
    for key in [k for k in sys.modules if k == NAME or k.startswith(NAME + '.')]:
        del sys.modules[key]


PLAIN = f"""
import {NAME}.ml
import {NAME}.viz
"""


def test_deferred_subpackages_load_at_their_first_use_as_their_own(fake):
    fake(PLAIN)
    package = import_deferring(NAME, ('ml', 'viz'))
    assert f'{NAME}.ml' not in sys.modules and f'{NAME}.viz' not in sys.modules
    assert isinstance(package.ml, DeferredModule) and 'deferred' in repr(package.ml)
    assert package.ml.VALUE == 42  # the first attribute imports it
    real = sys.modules[f'{NAME}.ml']
    assert not isinstance(real, DeferredModule) and package.ml is real
    viz = importlib.import_module(f'{NAME}.viz')  # an import statement gets the real one too
    assert viz.SHOWN and package.viz is viz and not isinstance(viz, DeferredModule)


def test_a_package_already_imported_is_returned_as_it_is(fake):
    fake(PLAIN)
    package = importlib.import_module(NAME)
    assert import_deferring(NAME, ('ml', 'viz')) is package
    assert not isinstance(package.ml, DeferredModule)


def test_a_subpackage_used_during_the_import_is_imported_there(fake):
    fake(PLAIN + f'from {NAME}.ml import VALUE\n')
    package = import_deferring(NAME, ('ml', 'viz'))
    assert package.VALUE == 42
    assert package.ml is sys.modules[f'{NAME}.ml'] and not isinstance(package.ml, DeferredModule)
    assert isinstance(package.viz, DeferredModule)


def test_an_import_that_fails_with_placeholders_is_done_plainly(fake):
    # The package attribute is set by a real import only: with a placeholder it is missing.
    fake(PLAIN + f'import {NAME}.helper\nDOUBLE = 2 * {NAME}.ml.VALUE\n',
         {'helper.py': 'HELPS = True\n'})
    package = import_deferring(NAME, ('ml', 'viz'))
    assert package.DOUBLE == 84
    for sub in ('ml', 'viz', 'helper'):  # each on the package, as a plain import sets them
        assert getattr(package, sub) is sys.modules[f'{NAME}.{sub}']
        assert not isinstance(getattr(package, sub), DeferredModule)


def test_an_import_that_fails_plainly_raises_its_error(fake):
    fake(PLAIN + 'raise RuntimeError("broken install")\n')
    with pytest.raises(RuntimeError, match='broken install'):
        import_deferring(NAME, ('ml', 'viz'))
    assert not any(isinstance(m, DeferredModule) for m in sys.modules.values())


def test_compiled_aliases_that_would_hide_a_python_module_are_dropped(fake):
    # As Open3D names its compiled submodules under the Python ones when none was imported.
    fake(PLAIN + textwrap.dedent(f"""
        import sys, types
        for sub in ('contrib', 'native'):
            sys.modules[f'{NAME}.ml.' + sub] = types.ModuleType(f'{NAME}.compiled.' + sub)
        """), {'ml/contrib/__init__.py': 'FROM_PYTHON = True\n'})
    import_deferring(NAME, ('ml', 'viz'))
    assert f'{NAME}.ml.contrib' not in sys.modules  # its Python package comes with the real ml
    assert sys.modules[f'{NAME}.ml.native'].__name__ == f'{NAME}.compiled.native'
    contrib = importlib.import_module(f'{NAME}.ml.contrib')
    assert contrib.FROM_PYTHON


def test_a_deferred_module_lists_the_real_ones_names(fake):
    fake(PLAIN)
    assert 'VALUE' in dir(import_deferring(NAME, ('ml', 'viz')).ml)


# What a process holds of Open3D: each entry's module name, and whether its parent has it.
SIGNATURE = """
import json, sys
mods = {k: v.__name__ for k, v in sys.modules.items() if k.startswith('open3d')}
parents = {k: getattr(sys.modules[k.rpartition('.')[0]], k.rpartition('.')[2], None)
           is sys.modules[k] for k in mods if k.rpartition('.')[0] in sys.modules}
print(json.dumps([mods, parents]))
"""
JUPYTER = """
import builtins
class ZMQInteractiveShell: pass
builtins.get_ipython = ZMQInteractiveShell  # what Open3D's __init__ asks of a notebook
"""
SHIM = """
from cgags_ros.open3d_import import open3d
import open3d.visualization
assert open3d.ml.datasets.__name__ == 'open3d.ml.datasets'  # its first use imports it
"""
LEFT_OUT = """
import sys
assert 'open3d.ml' not in sys.modules and 'open3d.visualization' not in sys.modules
"""


def _run(code: str) -> str:
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True, cwd=ROOT, timeout=300).stdout.splitlines()[-1]


@pytest.mark.subprocess
def test_open3d_once_its_subpackages_are_imported_is_as_a_plain_import_makes_it():
    plain = json.loads(_run('import open3d, open3d.ml, open3d.visualization' + SIGNATURE))
    assert plain[0]['open3d.ml.contrib'] == 'open3d.ml.contrib'  # the alias case is real
    shim = SHIM.replace('import open3d.visualization', LEFT_OUT + 'import open3d.visualization')
    assert json.loads(_run(shim + SIGNATURE)) == plain
    # In a notebook Open3D's __init__ uses open3d.visualization: the first attempt fails.
    assert json.loads(_run(JUPYTER + SHIM + SIGNATURE)) == plain
