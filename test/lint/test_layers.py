"""
The package's floors (README, "The floors"), checked on the source with ast.

1. ``filters``  2. ``presets``  3. ``estimator``, ``batch``, ``sim``, ``io``  4. ``ros``
5. ``replay``, ``evaluate``  6. ``tune``, ``plots``  7. ``cli``: a module imports only
from its own package or from a lower floor; the packages of one floor do not import
each other. ``core`` is the old API's re-export: it may import floors 1-3, and nothing
in kf_train imports it.

Libraries: only ``ros`` imports rclpy or message packages; only ``cli`` imports
argparse; only a package that starts processes (``cli``) imports subprocess. An
optional library (scipy, matplotlib, polars, dask, rosbags, tqdm, numba, pyproj) is imported
only by the package(s) that own its job (:data:`OPTIONAL`), and lazily: inside a
function, or at the top of a module that its package's ``__init__`` loads on first
use (listed in its ``_LAZY``, PEP 562). ``benchmarks/`` is outside the package.
Packages talk through their ``__init__``: an import from another package names the
package itself (``from kf_train.filters import X``), and X is public (no leading
underscore) and in that package's ``__all__``. The reference libraries (filterpy,
pykalman, simdkalman) are oracles of the tests and the benchmark only: kf_train never
imports them.
"""

import ast
import os
import re
from typing import Dict, List, Optional

import pytest

pytestmark = pytest.mark.linter

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PACKAGE_DIR = os.path.join(REPO, 'kf_train')
FLOORS = {'filters': 1, 'presets': 2, 'estimator': 3, 'batch': 3, 'sim': 3, 'io': 3,
          'ros': 4, 'replay': 5, 'evaluate': 5, 'tune': 6, 'plots': 6, 'cli': 7}
COMPATIBILITY = 'core'
ROS_ONLY = ('rclpy', 'rosidl_runtime_py', 'rosgraph_msgs', 'builtin_interfaces',
            'rcl_interfaces')
# Standard library modules only some packages may import: the package(s) allowed.
RESTRICTED = {'argparse': ('cli',), 'subprocess': ('cli',)}
# Optional libraries (extras): the package(s) owning their job; imported lazily.
OPTIONAL = {'scipy': ('tune',), 'matplotlib': ('plots',), 'polars': ('io',),
            'dask': ('replay',), 'rosbags': ('io',), 'tqdm': ('replay',),
            'numba': ('filters', 'batch'), 'pyproj': ('io',)}
ORACLES = ('filterpy', 'pykalman', 'simdkalman')


def _is_ros(module: str) -> bool:
    """Return whether ``module`` is rclpy or a ROS message package."""
    top = module.split('.')[0]
    return top in ROS_ONLY or top.endswith(('_msgs', '_srvs', '_interfaces'))


def _imports(tree: ast.AST, in_function: bool = False):
    """Yield (module, names or None, line, in a function) of every import, nested ones too."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, None, node.lineno, in_function
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module, [alias.name for alias in node.names], node.lineno, in_function
        inside = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                  ast.Lambda))
        yield from _imports(node, inside)


def lazy_modules(package_init_source: str) -> List[str]:
    """Return the modules a package's ``__init__`` loads on first use (its ``_LAZY``)."""
    for node in ast.parse(package_init_source).body:
        if isinstance(node, ast.Assign) and any(
                isinstance(target, ast.Name) and target.id == '_LAZY'
                for target in node.targets):
            return list(ast.literal_eval(node.value))
    return []


def exported_names(package_init_source: str) -> Optional[List[str]]:
    """Return the ``__all__`` a package's ``__init__`` assigns, or None."""
    for node in ast.parse(package_init_source).body:
        if isinstance(node, ast.Assign) and any(
                isinstance(target, ast.Name) and target.id == '__all__'
                for target in node.targets):
            return [ast.literal_eval(element) for element in node.value.elts]
    return None


def _library_rules(package: Optional[str], top: str, in_function: bool,
                   lazy_module: bool) -> List[str]:
    """Return the library rules an import of ``top`` breaks (messages without the place)."""
    if top in RESTRICTED and package not in RESTRICTED[top]:
        owners = ' and '.join(f'kf_train.{owner}' for owner in RESTRICTED[top])
        return [f'only {owners} imports {top}']
    if top not in OPTIONAL:
        return []
    if package not in OPTIONAL[top]:
        owners = ' and '.join(f'kf_train.{owner}' for owner in OPTIONAL[top])
        return [f'{top} is optional: only {owners} (its job) imports it']
    if not in_function and not lazy_module:
        return [f'{top} is optional: import it inside the function that needs it (or in '
                "a module the package's __init__ lists in _LAZY)"]
    return []


def violations(package: Optional[str], source: str, exports: Dict[str, List[str]],
               where: str = '<source>', lazy_module: bool = False) -> List[str]:
    """
    Return every rule that ``source``, a module of kf_train/``package``, breaks.

    ``package`` is None for a module directly in kf_train/; ``exports`` maps each
    package to its ``__all__``; ``lazy_module``: the package's ``__init__`` loads this
    module on first use (its ``_LAZY``), so its top-level imports are lazy too.
    """
    found = []
    for module, names, line, in_function in _imports(ast.parse(source)):
        at = f'{where}:{line}: {module}'
        top = module.split('.')[0]
        if _is_ros(module) and package != 'ros':
            found.append(f'{at}: only kf_train.ros imports rclpy and message packages')
        found += [f'{at}: {rule}' for rule in _library_rules(package, top, in_function,
                                                             lazy_module)]
        if top in ORACLES:
            found.append(f'{at}: {top} is a test and benchmark oracle, not a dependency')
        parts = module.split('.')
        if parts[0] != 'kf_train' or len(parts) == 1:
            continue
        target = parts[1]
        if target == package:
            continue
        if target == COMPATIBILITY:
            found.append(f'{at}: kf_train.core is the old API for users, not for kf_train')
            continue
        if target not in FLOORS:
            found.append(f'{at}: kf_train.{target} is not a floor')
            continue
        own = 3.5 if package == COMPATIBILITY else FLOORS.get(package, 0)
        if FLOORS[target] >= own:
            found.append(f'{at}: kf_train.{package} (floor {own}) may not import '
                         f'kf_train.{target} (floor {FLOORS[target]}): imports point down')
        if len(parts) > 2 or names is None:
            found.append(f'{at}: import from the package, "from kf_train.{target} import '
                         '...", not from its modules')
            continue
        for name in names:
            if name.startswith('_'):
                found.append(f'{at}: {name} is private to kf_train.{target}')
            elif name not in exports.get(target, ()):
                found.append(f'{at}: {name} is not in kf_train.{target}.__all__')
    return found


def _package_sources():
    """Yield (package or None, path, source, lazily loaded) of every module of kf_train."""
    for directory, _, files in sorted(os.walk(PACKAGE_DIR)):
        if '__pycache__' in directory.split(os.sep):
            continue  # bytecode a run outside the test suite left behind
        relative = os.path.relpath(directory, PACKAGE_DIR)
        package = None if relative == '.' else relative.split(os.sep)[0]
        lazy = []
        if package is not None and relative == package:
            with open(os.path.join(directory, '__init__.py'), encoding='utf-8') as stream:
                lazy = lazy_modules(stream.read())
        for name in sorted(files):
            if name.endswith('.py'):
                path = os.path.join(directory, name)
                with open(path, encoding='utf-8') as stream:
                    yield package, path, stream.read(), name[:-3] in lazy


def _exports() -> Dict[str, List[str]]:
    """Return every package's ``__all__`` (packages without one export nothing)."""
    exports = {}
    for package in list(FLOORS) + [COMPATIBILITY]:
        with open(os.path.join(PACKAGE_DIR, package, '__init__.py'), encoding='utf-8') as stream:
            exports[package] = exported_names(stream.read()) or []
    return exports


def test_the_floors_are_the_packages():
    """kf_train holds exactly the floors and core; every package exports its API."""
    entries = sorted(entry for entry in os.listdir(PACKAGE_DIR)
                     if os.path.isdir(os.path.join(PACKAGE_DIR, entry))
                     and not entry.startswith(('_', '.')))
    assert entries == sorted(list(FLOORS) + [COMPATIBILITY])
    assert [name for name in os.listdir(PACKAGE_DIR) if name.endswith('.py')] == [
        '__init__.py']
    exports = _exports()
    for package, names in exports.items():
        assert names, f'kf_train.{package}/__init__.py has no __all__'
        assert not [name for name in names if name.startswith('_')], package


def test_every_module_keeps_to_its_floor():
    """No import in kf_train breaks a rule of the floors."""
    exports = _exports()
    found = []
    for package, path, source, lazy in _package_sources():
        found += violations(package, source, exports, os.path.relpath(path, PACKAGE_DIR), lazy)
    assert not found, '\n'.join(found)


def test_every_exported_name_exists():
    """Each name in a package's __all__ is importable from it (the rules rely on it)."""
    import importlib
    for package, names in _exports().items():
        if package in ('ros', 'cli'):
            continue  # imported lazily or with rclpy: their modules are tested apart
        module = importlib.import_module(f'kf_train.{package}')
        missing = [name for name in names if not hasattr(module, name)]
        assert not missing, f'kf_train.{package}.__all__ names missing: {missing}'


EXPORTS = {'filters': ['predict', 'kalman'], 'presets': ['load_preset'],
           'estimator': ['StreamEstimator'], 'sim': ['TrainSimulation'], 'tune': ['fit'],
           'replay': ['run'], 'cli': ['main']}


@pytest.mark.parametrize('package, source, rule', [
    ('filters', 'from kf_train.presets import load_preset\n', 'imports point down'),
    ('estimator', 'from kf_train.sim import TrainSimulation\n', 'imports point down'),
    ('presets', 'from kf_train.filters.kalman import predict\n', 'not from its modules'),
    ('presets', 'import kf_train.filters\n', 'not from its modules'),
    ('presets', 'from kf_train.filters import _private\n', 'private'),
    ('presets', 'from kf_train.filters import secret\n', 'not in kf_train.filters.__all__'),
    ('sim', 'def f():\n    import rclpy\n', 'only kf_train.ros imports rclpy'),
    ('cli', 'from nav_msgs.msg import Odometry\n', 'only kf_train.ros imports rclpy'),
    ('ros', 'import argparse\n', 'only kf_train.cli imports argparse'),
    ('tune', 'def f():\n    import argparse\n', 'only kf_train.cli imports argparse'),
    ('batch', 'import subprocess\n', 'only kf_train.cli imports subprocess'),
    ('filters', 'def f():\n    from matplotlib.figure import Figure\n',
     'matplotlib is optional: only kf_train.plots'),
    ('batch', 'def f():\n    from scipy import optimize\n',
     'scipy is optional: only kf_train.tune'),
    ('replay', 'def f():\n    import polars\n', 'polars is optional: only kf_train.io'),
    ('cli', 'def f():\n    import tqdm\n', 'tqdm is optional: only kf_train.replay'),
    ('tune', 'def f():\n    from rosbags.rosbag2 import Reader\n',
     'rosbags is optional: only kf_train.io'),
    ('evaluate', 'def f():\n    import dask.dataframe\n', 'dask is optional'),
    ('plots', 'def f():\n    import numba\n', 'numba is optional'),
    ('plots', 'from matplotlib.figure import Figure\n', 'import it inside the function'),
    ('tune', 'import scipy.optimize\n', 'import it inside the function'),
    ('tune', 'class A:\n    from scipy import optimize\n', 'import it inside the function'),
    ('io', 'try:\n    import polars\nexcept ImportError:\n    pass\n',
     'import it inside the function'),
    ('replay', 'from kf_train.tune import fit\n', 'imports point down'),
    ('plots', 'from kf_train.cli import main\n', 'imports point down'),
    ('batch', 'import filterpy.kalman\n', 'oracle'),
    ('cli', 'from kf_train.core import TrainEstimator\n', 'old API'),
    (None, 'from kf_train.estimator import StreamEstimator\n', 'imports point down'),
])
def test_the_checker_finds_each_kind_of_violation(package, source, rule):
    """The rules are not vacuous: a module breaking one is reported, with the rule."""
    found = violations(package, source, EXPORTS)
    assert found and all(rule in message for message in found[:1]), found


@pytest.mark.parametrize('package, source', [
    ('cli', 'from kf_train.filters import kalman, predict\nimport argparse\n'),
    ('ros', 'import rclpy\nfrom kf_train.estimator import StreamEstimator\n'),
    ('estimator', 'from kf_train.estimator.contract import Rejected\n'),
    ('core', 'from kf_train.sim import TrainSimulation\n'),
    ('tune', 'def f():\n    from scipy import optimize\n'),
    ('plots', 'def f():\n    from matplotlib.figure import Figure\n'),
    ('io', 'def f():\n    import polars\n'),
    ('replay', 'def f():\n    import dask.dataframe as dd\n    from tqdm import tqdm\n'),
])
def test_the_checker_passes_what_the_rules_allow(package, source):
    """Downward package imports, the own package's modules and allowed libraries pass."""
    assert violations(package, source, EXPORTS) == []


def test_a_lazily_loaded_module_may_import_its_library_at_the_top():
    """A module the package's __init__ lists in _LAZY imports its library when loaded."""
    source = 'from rosbags.rosbag2 import Reader\n'
    assert violations('io', source, EXPORTS, lazy_module=True) == []
    assert violations('io', source, EXPORTS)
    init = "_LAZY = ('bagio', 'bagio_output')\n"
    assert lazy_modules(init) == ['bagio', 'bagio_output']
    assert lazy_modules('__all__ = []\n') == []


def readme_floors(readme: str) -> Dict[str, int]:
    """Return {package: floor} as the README's drawing of the floors shows them."""
    section = readme.split('## The floors', 1)[1].split('```text', 1)[1].split('```', 1)[0]
    floors, floor = {}, None
    for line in section.splitlines():
        match = re.match(r'^ ?(\d)?\s+([a-z_]+)/\s', line + ' ')
        if not match:
            continue
        if match.group(1):
            floor = int(match.group(1))
        floors[match.group(2)] = floor
    return floors


def test_the_readme_draws_the_floors_the_checker_enforces():
    """The README's drawing of the floors names exactly the packages and floors of FLOORS."""
    with open(os.path.join(REPO, 'README.md'), encoding='utf-8') as stream:
        drawn = readme_floors(stream.read())
    drawn.pop(COMPATIBILITY, None)
    assert drawn == FLOORS
    # The parser reads what it is given: a drawing with a wrong floor differs.
    assert readme_floors('## The floors\n```text\n 2  cli/   x\n    io/   y\n```\n') == {
        'cli': 2, 'io': 2}


CLI_MAX_LINES = 2500
MODULE_MAX_LINES = 600
FUNCTION_MAX_LINES = 80


def oversized(path: str, source: str) -> List[str]:
    """Return what in one module is over the size limits (the module, its functions)."""
    found = []
    if source.count('\n') > MODULE_MAX_LINES:
        found.append(f'{path}: {source.count(chr(10))} lines (limit {MODULE_MAX_LINES})')
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            if length > FUNCTION_MAX_LINES:
                found.append(f'{path}:{node.lineno}: {node.name} is {length} lines '
                             f'(limit {FUNCTION_MAX_LINES})')
    return found


def test_the_rooms_stay_small():
    """The command line only parses and prints; no module or function grows past a page."""
    found, cli_lines = [], 0
    for package, path, source, _ in _package_sources():
        found += oversized(os.path.relpath(path, REPO), source)
        cli_lines += source.count('\n') if package == 'cli' else 0
    assert not found, '\n'.join(found)
    assert cli_lines <= CLI_MAX_LINES, f'kf_train/cli/ holds {cli_lines} lines'
    long_function = 'def f():\n' + '    x = 1\n' * FUNCTION_MAX_LINES
    assert oversized('m.py', long_function) == ['m.py:1: f is 81 lines (limit 80)']
