"""The package's layout bars: no module over 700 lines, no private name taken across modules."""

import ast
from pathlib import Path

import pytest

# the repository root: the nearest folder above this file with package.xml (wherever the
# test folders put this file)
REPO = next(p for p in Path(__file__).resolve().parents if (p / 'package.xml').is_file())
PACKAGE = REPO / 'observer_ros'
MAX_LINES = 700


def _module_name(path, root):
    """Dotted name of the module at ``path`` (a package's ``__init__.py`` is the package)."""
    parts = list(path.relative_to(root.parent).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def _is_private(name):
    return name.startswith('_') and not name.startswith('__')


def _resolve(node, module, is_package):
    """Absolute module named by an ``ImportFrom`` node in ``module``."""
    if node.level == 0:
        return node.module or ''
    package = module.split('.') if is_package else module.split('.')[:-1]
    base = package[:len(package) - node.level + 1]
    return '.'.join(base + ([node.module] if node.module else []))


def _modules(root):
    names = {}
    for path in sorted(root.rglob('*.py')):
        names[_module_name(path, root)] = path
    return names


def private_imports(root):
    """
    Every place where a module takes another module's private name.

    A private name is one with a single leading underscore. Two forms are found:
    ``from mod import _name`` and ``mod._name`` where ``mod`` is a module of the package
    bound by an import in that file. A private module may be imported by its own package's
    modules (``from . import _helper``). Returns ``file:line: text`` strings.
    """
    top = root.name
    modules = _modules(root)
    found = []
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        is_package = path.name == '__init__.py'
        own_package = module if is_package else module.rpartition('.')[0]
        bound = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                source = _resolve(node, module, is_package)
                if source != top and not source.startswith(top + '.'):
                    continue
                for alias in node.names:
                    full = source + '.' + alias.name
                    if full in modules:
                        bound[alias.asname or alias.name] = full
                    if not _is_private(alias.name):
                        continue
                    if full in modules and source == own_package:
                        continue
                    found.append('%s:%d: from %s import %s'
                                 % (path.relative_to(root.parent), node.lineno, source,
                                    alias.name))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith(top + '.') and alias.asname:
                        bound[alias.asname] = alias.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and _is_private(node.attr)
                    and isinstance(node.value, ast.Name) and node.value.id in bound):
                found.append('%s:%d: %s.%s' % (path.relative_to(root.parent), node.lineno,
                                               bound[node.value.id], node.attr))
    return found


def long_modules(root, limit=MAX_LINES):
    """``(path, lines)`` of every module of ``root`` longer than ``limit`` lines."""
    out = []
    for path in sorted(root.rglob('*.py')):
        lines = len(path.read_text().splitlines())
        if lines > limit:
            out.append((str(path.relative_to(root.parent)), lines))
    return out


def test_no_module_is_over_700_lines():
    assert long_modules(PACKAGE) == []


def test_no_module_takes_a_private_name_of_another():
    found = private_imports(PACKAGE)
    assert found == [], 'private names taken across modules:\n' + '\n'.join(found)


@pytest.fixture
def toy_package(tmp_path):
    root = tmp_path / 'toy'
    (root / 'sub').mkdir(parents=True)
    (root / '__init__.py').write_text('')
    (root / 'sub' / '__init__.py').write_text('from . import _helper\n')
    (root / 'sub' / '_helper.py').write_text('X = 1\n_Y = 2\n')
    (root / 'a.py').write_text('_SECRET = 1\n\ndef _f():\n    return 1\n')
    return root


def test_the_checker_finds_each_form_of_private_import(toy_package):
    (toy_package / 'b.py').write_text(
        'from .a import _SECRET\n'
        'from toy.a import _f\n'
        'from . import a\n'
        'import toy.a as alias\n'
        'from .sub import _helper\n'
        'print(a._f(), alias._SECRET, _helper.X, _helper._Y)\n')
    found = private_imports(toy_package)
    assert sorted(f.split(': ', 1)[1] for f in found) == [
        'from toy.a import _SECRET', 'from toy.a import _f', 'from toy.sub import _helper',
        'toy.a._SECRET', 'toy.a._f', 'toy.sub._helper._Y']


def test_the_checker_passes_public_names_and_a_package_own_private_module(toy_package):
    (toy_package / 'sub' / 'c.py').write_text(
        'from . import _helper\nfrom ..a import _SECRET as public\n')
    (toy_package / 'd.py').write_text('import os\nfrom .sub._helper import X\nos._exit\n')
    found = private_imports(toy_package)
    assert [f.split(': ', 1)[1] for f in found] == ['from toy.a import _SECRET']


def test_the_line_count_bar_names_a_long_module(toy_package):
    (toy_package / 'long.py').write_text('x = 1\n' * 701)
    assert long_modules(toy_package) == [('toy/long.py', 701)]
