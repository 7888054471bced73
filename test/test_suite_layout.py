# The suite's own rules: folders that mirror the package, fixtures shared through conftest.py.
"""Test modules import helpers, never another test module; each folder names a concern."""

import ast
from pathlib import Path
import re

from ros_helpers import FIRST_DOMAIN

TEST = Path(__file__).resolve().parent
PACKAGE = TEST.parent / 'observer_ros'
# test folders that are not a package of observer_ros: the whole system, and the tools'
# command lines and outputs (observer_ros/tools and observer_ros/outputs)
OTHER_FOLDERS = {'system', 'tools'}


def _modules():
    return sorted(p for p in TEST.rglob('*.py') if '__pycache__' not in p.parts)


def test_no_test_module_imports_another():
    offenders = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            offenders += [f'{path.relative_to(TEST)}:{node.lineno}: {name}'
                          for name in names if name.split('.')[0].startswith('test_')]
    assert not offenders, 'shared code goes to a helper module or conftest.py: ' + \
        ', '.join(offenders)


def test_every_test_folder_mirrors_a_package_folder():
    folders = {p.name for p in TEST.iterdir() if p.is_dir() and p.name != '__pycache__'}
    packages = {p.name for p in PACKAGE.iterdir() if (p / '__init__.py').is_file()}
    assert folders - OTHER_FOLDERS <= packages, folders - OTHER_FOLDERS - packages
    assert all(any(p.glob('test_*.py')) for p in map(TEST.joinpath, folders))


def test_module_basenames_are_unique():
    # test/ has no __init__.py: pytest imports each module by its file name alone
    names = [p.name for p in _modules()]
    assert len(names) == len(set(names)), sorted(n for n in names if names.count(n) > 1)


def test_make_test_runs_the_realtime_tests_one_at_a_time_above_the_workers_priority():
    # realtime closed loops beside each other on 2 cores fail; the rest runs in workers at
    # a lower priority beside them, the realtime ones in a DDS domain below the workers'
    make = (TEST.parent / 'Makefile').read_text()
    pytest_command = re.search(r'^PYTEST := (.+)$', make, re.M).group(1)
    recipe = make.split('\ntest: ')[1].split('\n\n')[0].replace('$(PYTEST)', pytest_command)
    runs = [r for r in recipe.replace('\\\n', ' ').split(';') if '-m pytest' in r]
    assert len(runs) == 2, runs
    workers = [r for r in runs if '-m "not realtime"' in r]
    realtime = [r for r in runs if '-m realtime' in r]
    assert len(workers) == len(realtime) == 1, runs
    assert '-n ' in workers[0] and 'nice -n $(WORKERS_NICE)' in workers[0], workers[0]
    # nice runs a program: an environment assignment right after it is not one
    niced = workers[0].split('nice -n $(WORKERS_NICE)')[1].split()[0]
    assert '=' not in niced, workers[0]
    assert '-n ' not in realtime[0] and 'nice' not in realtime[0], realtime[0]
    assert 'OBSERVER_TEST_DOMAIN_ID=$(REALTIME_DOMAIN_ID)' in realtime[0], realtime[0]
    domain = re.search(r'^REALTIME_DOMAIN_ID \?= (\d+)$', make, re.M)
    assert domain and int(domain.group(1)) < FIRST_DOMAIN, "below the workers' domains"
    nice = re.search(r'^WORKERS_NICE \?= (\d+)$', make, re.M)
    assert nice and 0 < int(nice.group(1)) < 19, 'lower than the realtime tests, not starved'
