# Copyright 2017 Open Source Robotics Foundation, Inc.
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

import ast
import configparser
from pathlib import Path

from ament_flake8.main import main_with_errors
import ament_pep257.main
from flake8.plugins import finder
import pydocstyle
import pytest

# Explicit paths, so .venv and colcon's build/, install/ and log/ are never linted.
PATHS = ['observer_ros', 'test', 'benchmarks', 'setup.py']

# flake8-docstrings runs pydocstyle, with the pep257 convention's codes less ament's
# ignores; test_pep257.py runs pydocstyle over the same paths with every code less the same
# ignores, a superset (test_the_docstring_rules_are_checked_by_test_pep257). The plugin is
# left out here, so that each file's docstrings are parsed once, not twice (a fifth of
# flake8's time).
DOCSTRINGS_PLUGIN = 'flake8-docstrings'


def _without_docstrings(find_plugins):
    def find(cfg, opts):
        return [p for p in find_plugins(cfg, opts) if p.package != DOCSTRINGS_PLUGIN]
    return find


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch):
    monkeypatch.setattr(finder, 'find_plugins', _without_docstrings(finder.find_plugins))
    rc, errors = main_with_errors(argv=PATHS)
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + \
        '\n'.join(errors)


def test_the_docstring_rules_are_checked_by_test_pep257():
    ini = Path(ament_pep257.main.__file__).parents[1] / 'ament_flake8' / 'configuration' / \
        'ament_flake8.ini'
    config = configparser.ConfigParser()
    config.read(ini)
    ignored = {c.strip() for c in config['flake8']['extend-ignore'].split(',')}
    by_flake8 = set(pydocstyle.conventions['pep257']) - ignored
    every = set(pydocstyle.violations.ErrorRegistry.get_error_codes())
    by_pep257 = every - set(ament_pep257.main._ament_ignore)
    assert by_flake8 and by_flake8 <= by_pep257, sorted(by_flake8 - by_pep257)
    # over the same paths
    tree = ast.parse((Path(__file__).parent / 'test_pep257.py').read_text())
    paths = [ast.literal_eval(node.value) for node in tree.body
             if isinstance(node, ast.Assign) and node.targets[0].id == 'PATHS']
    assert paths == [PATHS]
    # the plugin is installed (it is what ament_flake8 would run) and left out
    plugins = finder.find_plugins(configparser.RawConfigParser(),
                                  finder.PluginOptions.blank())
    assert any(p.package == DOCSTRINGS_PLUGIN for p in plugins)
    assert not any(p.package == DOCSTRINGS_PLUGIN for p in
                   _without_docstrings(finder.find_plugins)(
                       configparser.RawConfigParser(), finder.PluginOptions.blank()))
