"""
Every repository path the documentation names exists.

README.md and docs/*.md (their text and their relative Markdown links), and the
docstrings and comments of kf_train/, benchmarks/ and tools/, name files as
``kf_train/ros/session.py``, ``test/lint/test_layers.py``, ``docs/rail.md`` and modules
as ``kf_train.batch.partition.filter_partition``. A file that moves leaves such names
behind, and nothing else notices: this test lists every one that no longer exists.

What counts as a repository path: a token that starts with one of :data:`ROOTS` and is
not part of a longer path (``../shared/x``, ``install/kf_train/share/...``, a URL).
Globs (``*``, ``?``, ``[``, ``{``, ``<``), elisions (``...``) and other roots (example
outputs such as ``out/demo/...``) are not checked. A dotted name ``kf_train.a.b`` must
resolve to a package or module, and the first name after the module, if any, must be
defined at its top level (a file name such as ``kf_train.launch.py`` is not a module).
"""

import ast
import io
import os
import re
import tokenize
from typing import Iterator, List, Set

import pytest

pytestmark = pytest.mark.linter

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ROOTS = ('kf_train', 'test', 'docs', 'benchmarks', 'tools', 'config', 'launch', 'resource')
SOURCE_DIRS = ('kf_train', 'benchmarks', 'tools')
README_MAX_LINES = 300
# A path token: a root, a slash, then path characters; globs are matched so as to be
# recognised (and skipped) whole. Not preceded by a path character, a ':' (URL) or '~'.
_PATH = re.compile(r'(?<![\w./~:-])((?:' + '|'.join(ROOTS) + r')/[\w./*?{}<>\[\]-]*)')
_GLOB = set('*?{}<>[]')
_DOTTED = re.compile(r'(?<![\w./-])(kf_train(?:\.[A-Za-z_]\w*)+)(?![\w-])')
_FILE_SUFFIXES = {'py', 'yaml', 'yml', 'md', 'csv', 'txt', 'png', 'mcap', 'json', 'launch',
                  'xml', 'cfg', 'parquet', 'db3'}
_LINK = re.compile(r'\]\(([^)\s]+)\)')


def path_tokens(text: str) -> Iterator[str]:
    """Yield every repository path ``text`` names (globs and elisions left out)."""
    for match in _PATH.finditer(text):
        token = match.group(1).rstrip('.,;:')
        if _GLOB & set(token) or '...' in token or '//' in token:
            continue
        yield token


def dotted_tokens(text: str) -> Iterator[str]:
    """Yield every dotted ``kf_train.x.y`` name in ``text`` that is not a file name."""
    for match in _DOTTED.finditer(text):
        token = match.group(1)
        if token.split('.')[-1] not in _FILE_SUFFIXES:
            yield token


def link_targets(text: str) -> Iterator[str]:
    """Yield the relative targets of the Markdown links in ``text`` (anchors cut off)."""
    for match in _LINK.finditer(text):
        target = match.group(1).split('#')[0]
        if target and '://' not in target and not target.startswith('mailto:'):
            yield target


def _top_level_names(path: str) -> Set[str]:
    """Return the names a module defines at its top level ('*' if it may define any)."""
    with open(path, encoding='utf-8') as stream:
        tree = ast.parse(stream.read())
    names, lazy = set(), None
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
            if node.name == '__getattr__':
                names.add('*')
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                names |= {n.id for n in ast.walk(target) if isinstance(n, ast.Name)}
                if isinstance(target, ast.Name) and target.id == '_LAZY':
                    lazy = set(ast.literal_eval(node.value))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                names.add('*' if alias.name == '*' else
                          (alias.asname or alias.name).split('.')[0])
    if '*' in names and lazy is not None and not any(
            isinstance(node, ast.ImportFrom) and any(a.name == '*' for a in node.names)
            for node in tree.body):
        names = (names - {'*'}) | lazy  # a PEP 562 __getattr__ of the modules in _LAZY
    return names


def module_exists(dotted: str, root: str = REPO) -> bool:
    """Return whether ``dotted`` names a package, a module or a name a module defines."""
    parts = dotted.split('.')
    here = os.path.join(root, parts[0])
    for index, part in enumerate(parts[1:], start=1):
        if os.path.isdir(os.path.join(here, part)) and os.path.isfile(
                os.path.join(here, part, '__init__.py')):
            here = os.path.join(here, part)
        elif os.path.isfile(os.path.join(here, part + '.py')):
            here = os.path.join(here, part + '.py')
            return index == len(parts) - 1 or _defines(here, parts[index + 1])
        else:
            return os.path.isdir(here) and _defines(os.path.join(here, '__init__.py'), part)
    return True


def _defines(path: str, name: str) -> bool:
    """Return whether the module file ``path`` defines ``name`` at its top level."""
    if not os.path.isfile(path):
        return False
    names = _top_level_names(path)
    return name in names or '*' in names


def missing_paths(text: str, base: str, root: str = REPO) -> List[str]:
    """
    Return the repository paths, modules and links ``text`` names that do not exist.

    Paths and modules are relative to ``root``; Markdown links to the directory
    ``base`` of the file they are in (pass None for text that is not Markdown).
    """
    missing = [token for token in path_tokens(text)
               if not os.path.exists(os.path.join(root, token))]
    missing += [token for token in dotted_tokens(text) if not module_exists(token, root)]
    if base is not None:
        missing += [target for target in link_targets(text)
                    if not os.path.exists(os.path.normpath(os.path.join(base, target)))]
    return missing


def docstrings_and_comments(source: str) -> str:
    """Return the docstrings and comments of a Python source, one after another."""
    texts = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                             ast.AsyncFunctionDef)):
            docstring = ast.get_docstring(node, clean=False)
            if docstring:
                texts.append(docstring)
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            texts.append(token.string)
    return '\n'.join(texts)


def _markdown_files() -> List[str]:
    """Return README.md and every docs/*.md."""
    docs = os.path.join(REPO, 'docs')
    return [os.path.join(REPO, 'README.md')] + sorted(
        os.path.join(docs, name) for name in os.listdir(docs) if name.endswith('.md'))


def _python_files() -> List[str]:
    """Return every .py file under kf_train/, benchmarks/ and tools/."""
    found = []
    for top in SOURCE_DIRS:
        for folder, _, files in os.walk(os.path.join(REPO, top)):
            found += [os.path.join(folder, name) for name in files if name.endswith('.py')]
    return sorted(found)


def _read(path: str) -> str:
    """Return a file's text."""
    with open(path, encoding='utf-8') as stream:
        return stream.read()


@pytest.mark.parametrize('path', _markdown_files(), ids=lambda p: os.path.relpath(p, REPO))
def test_every_path_the_docs_name_exists(path):
    """README.md and docs/*.md name only paths, modules and link targets that exist."""
    missing = missing_paths(_read(path), os.path.dirname(path))
    assert not missing, f'{os.path.relpath(path, REPO)} names missing {sorted(set(missing))}'


def test_every_path_the_docstrings_and_comments_name_exists():
    """Docstrings and comments in kf_train/, benchmarks/ and tools/ name existing paths."""
    found = []
    for path in _python_files():
        text = docstrings_and_comments(_read(path))
        found += [f'{os.path.relpath(path, REPO)}: {token}'
                  for token in sorted(set(missing_paths(text, None)))]
    assert not found, '\n'.join(found)


def test_the_checker_finds_what_is_missing_and_only_that():
    """The extractor flags missing paths and modules, and skips URLs, globs, examples."""
    sample = """
    See kf_train/filters/kalman.py, test/lint/test_layers.py and docs/rail.md; the
    folder kf_train/presets/ and `config/kf_train.yaml`. Moved: test/test_layers.py,
    kf_train/filters/nowhere.py. and docs/missing.md, and [the floors](docs/gone.md).
    Modules: kf_train.filters.kalman, kf_train.filters.kalman.predict, kf_train.filters
    (a package), :mod:`kf_train.filters.nowhere`, kf_train.filters.kalman.no_such_name.
    Not checked: https://github.com/o/r/blob/main/kf_train/absent.py, the glob
    kf_train/presets/*.yaml, out/demo/rail/rail.png, ../shared/seeds/x.md,
    install/kf_train/share/kf_train/config/absent.yaml, kf_train.launch.py,
    kf_train.yaml, kf_train/...py and [a section](#the-floors).
    """
    missing = missing_paths(sample, REPO)
    assert sorted(missing) == sorted([
        'test/test_layers.py', 'kf_train/filters/nowhere.py', 'docs/missing.md',
        'docs/gone.md', 'kf_train.filters.nowhere', 'kf_train.filters.kalman.no_such_name',
        'docs/gone.md']), missing
    assert docstrings_and_comments(
        '"""Module: docs/a.md."""\n\n\ndef f():\n    """F."""\n    return 1  # kf_train/b.py\n'
    ) == 'Module: docs/a.md.\nF.\n# kf_train/b.py'


def test_the_readme_is_short_and_links_every_reference_page():
    """README.md stays a newcomer's read and links each page of docs/."""
    text = _read(os.path.join(REPO, 'README.md'))
    assert text.count('\n') <= README_MAX_LINES
    linked = {os.path.normpath(target) for target in link_targets(text)}
    pages = {os.path.join('docs', name) for name in os.listdir(os.path.join(REPO, 'docs'))
             if name.endswith('.md')}
    assert not pages - linked, f'README.md does not link {sorted(pages - linked)}'


def test_the_performance_page_holds_one_whole_bench_table():
    """docs/performance.md holds one make-bench table with every row (1 to 11, and the soak)."""
    lines = _read(os.path.join(REPO, 'docs', 'performance.md')).splitlines()
    header = '| Row | Measurement | Case | Result | Ratio | Target |'
    assert lines.count(header) == 1
    rows = {line.split('|')[1].strip() for line in lines
            if line.startswith('| ') and line != header}
    assert rows == {'1', '2', '3', '4', '5', '6', '7', '8', '9', '10a', '10b', '11', 'soak'}
