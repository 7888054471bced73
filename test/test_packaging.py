# The package as a ROS 2 user gets it: colcon build, lib/observer_ros executables, share/.
"""Packaging: colcon build, installed executables and config, declared dependencies."""

import ast
import json
import os
from pathlib import Path
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

from ros_helpers import Probe, REPO, ros_env

EXECUTABLES = ('plant_simulator', 'observer', 'compensator', 'recorder', 'container',
               'observer_design', 'observer_eval', 'observer_eval_batch', 'observer_tune',
               'observer_play', 'observer_run', 'observer_bag_recover')

# import name -> the package.xml key that provides it
DEPENDENCY_KEYS = {
    'rclpy': 'rclpy', 'std_msgs': 'std_msgs', 'sensor_msgs': 'sensor_msgs',
    'diagnostic_msgs': 'diagnostic_msgs', 'rosgraph_msgs': 'rosgraph_msgs',
    'builtin_interfaces': 'builtin_interfaces', 'rcl_interfaces': 'rcl_interfaces',
    'ament_index_python': 'ament_index_python', 'numpy': 'python3-numpy',
    'scipy': 'python3-scipy', 'yaml': 'python3-yaml', 'matplotlib': 'python3-matplotlib',
    'control': 'python-control-pip', 'rosbags': 'python3-rosbags-pip',
    'launch': 'launch', 'launch_ros': 'launch_ros', 'std_srvs': 'std_srvs',
    'lifecycle_msgs': 'lifecycle_msgs',
}
# Keys rosdep resolves, as read from ros/rosdistro (master, 2026-11; see
# ../shared/ros2cli/README.md): ROS packages of the Jazzy distribution (jazzy/distribution.yaml)
# and system keys of rosdep/base.yaml and rosdep/python.yaml. A key not here is a typo or a
# key that does not exist (python3-control-pip did not: `rosdep install` failed on it).
KNOWN_ROSDEP_KEYS = {
    # jazzy/distribution.yaml (ROS packages)
    'rclpy', 'std_msgs', 'sensor_msgs', 'diagnostic_msgs', 'rosgraph_msgs',
    'builtin_interfaces', 'rcl_interfaces', 'ament_index_python', 'launch', 'launch_ros',
    'ament_flake8', 'ament_pep257', 'std_srvs', 'lifecycle_msgs',
    # rosdep/python.yaml
    'python3-numpy', 'python3-scipy', 'python3-yaml', 'python3-matplotlib', 'python3-pytest',
    'python3-hypothesis', 'python-control-pip', 'python3-rosbags-pip',
}
# optional imports guarded by ImportError (zstd and lz4 codecs for compressed chunks)
OPTIONAL_IMPORTS = {'backports', 'compression', 'lz4'}
# tool dependencies with no rosdep key, installed with pip (README's install notes);
# observer-eval-batch says so when they are missing
OPTIONAL_IMPORTS |= {'distributed'}
# only for observer-eval-batch --dashboard (the `dashboard` extra), which says so when missing
OPTIONAL_IMPORTS |= {'bokeh'}


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    ws = tmp_path_factory.mktemp('ws')
    colcon = Path(sys.executable).parent / 'colcon'
    result = subprocess.run(
        [str(colcon), 'build', '--base-paths', str(REPO), '--build-base', str(ws / 'build'),
         '--install-base', str(ws / 'install')],
        cwd=ws, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    return ws / 'install' / 'observer_ros'


def _installed_env(prefix):
    env = ros_env()
    site = next(prefix.glob('lib/python3*/site-packages'))
    env['PYTHONPATH'] = os.pathsep.join([str(site), env.get('PYTHONPATH', '')])
    env['AMENT_PREFIX_PATH'] = os.pathsep.join([str(prefix), sys.prefix])
    return env


@pytest.mark.ros
def test_colcon_installs_executables_where_ros2_run_looks(colcon_install):
    for exe in EXECUTABLES:
        assert (colcon_install / 'lib' / 'observer_ros' / exe).is_file(), exe
    # each executable once (no dash aliases: those are the venv's only)
    assert sorted(p.name for p in (colcon_install / 'lib' / 'observer_ros').iterdir()) == \
        sorted(EXECUTABLES)
    assert sorted(p.name for p in (colcon_install / 'share' / 'observer_ros' /
                                   'launch').iterdir()) == \
        ['closed_loop.launch.py', 'observer.launch.py']
    share = colcon_install / 'share' / 'observer_ros'
    assert (share / 'package.xml').is_file()
    assert sorted(p.name for p in (share / 'config').glob('*.yaml')) == \
        sorted(p.name for p in (REPO / 'config').glob('*.yaml'))
    assert (colcon_install / 'share' / 'ament_index' / 'resource_index' / 'packages' /
            'observer_ros').is_file()


@pytest.mark.ros
def test_installed_design_tool_runs_on_the_installed_config(colcon_install):
    env = _installed_env(colcon_install)
    exe = colcon_install / 'lib' / 'observer_ros' / 'observer_design'
    config = colcon_install / 'share' / 'observer_ros' / 'config' / 'submarine.yaml'
    result = subprocess.run([str(exe), str(config), '--json'], env=env, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report['observable'] and report['separation_ok']
    assert [v[0] for v in report['L']] == pytest.approx([-21.942, -2.2601, 0.7685], abs=1e-4)
    # the installed copy is the one imported, and ament_index finds the package
    where = subprocess.run(
        [sys.executable, '-c', 'import observer_ros; '
         'from ament_index_python.packages import get_package_share_directory as g; '
         'print(observer_ros.__file__); print(g("observer_ros"))'],
        env=env, capture_output=True, text=True, timeout=60, cwd=colcon_install)
    assert where.returncode == 0, where.stderr
    module, share = where.stdout.split()
    assert module.startswith(str(colcon_install)) and share.startswith(str(colcon_install))


@pytest.mark.ros
def test_installed_observer_node_runs_with_the_installed_config(colcon_install):
    env = _installed_env(colcon_install)
    exe = colcon_install / 'lib' / 'observer_ros' / 'observer'
    config = colcon_install / 'share' / 'observer_ros' / 'config' / 'submarine.yaml'
    proc = subprocess.Popen([str(exe), '--ros-args', '--params-file', str(config)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    probe = Probe()
    try:
        probe.wait_subscribers('imu/data')
        probe.wait_publishers('state/estimate')
    finally:
        probe.close()
        proc.send_signal(2)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert 'observable=True' in out


def _assert_runs_in_a_fresh_interpreter(code):
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr


@pytest.mark.ros
def test_core_and_offline_tools_import_no_ros():
    _assert_runs_in_a_fresh_interpreter(
        'import sys, observer_ros.core, observer_ros.vehicle, observer_ros.sensors, '
        'observer_ros.evaluation.evaluate, observer_ros.tools.design_report; '
        'bad = [m for m in sys.modules if m.split(".")[0] in '
        '("rclpy", "std_msgs", "sensor_msgs", "rcl_interfaces")]; '
        'assert not bad, bad')


@pytest.mark.ros
def test_offline_tools_import_python_control_only_when_they_design():
    """observer-eval replays with the file's gains: python-control (~1 s) is not loaded."""
    _assert_runs_in_a_fresh_interpreter(
        'import sys, observer_ros.core, observer_ros.evaluation.evaluate; '
        'assert "control" not in sys.modules, "imported at start"; '
        'from observer_ros.core import observer_gain; '
        'L = observer_gain([[0.0, 1.0], [0.0, 0.0]], [[1.0, 0.0]], [-1.0, -2.0], '
        'method="place"); '
        'assert "control" in sys.modules; '
        'assert abs(L[0, 0] - 3.0) < 1e-12 and abs(L[1, 0] - 2.0) < 1e-12, L')


def _third_party_imports():
    found = set()
    for path in (REPO / 'observer_ros').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split('.')[0])
    stdlib = set(sys.stdlib_module_names)
    return {name for name in found if name not in stdlib and name != 'observer_ros'}


def test_package_xml_declares_every_runtime_dependency():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    declared = {e.text for e in root if e.tag in ('exec_depend', 'depend')}
    imports = _third_party_imports() - OPTIONAL_IMPORTS
    unknown = imports - set(DEPENDENCY_KEYS)
    assert not unknown, f'imports with no known package.xml key: {unknown}'
    missing = {DEPENDENCY_KEYS[name] for name in imports} - declared
    assert not missing, f'package.xml lacks exec_depend {missing}'


def test_package_xml_uses_only_rosdep_keys_that_exist():
    root = ET.parse(REPO / 'package.xml').getroot()
    keys = {e.text.strip() for e in root if e.tag.endswith('depend')}
    assert {'launch', 'launch_ros', 'python-control-pip'} <= keys
    unknown = keys - KNOWN_ROSDEP_KEYS
    assert not unknown, f'package.xml names keys rosdep does not know: {sorted(unknown)}'


def test_the_set_up_leaves_the_installed_modules_compiled():
    # make's set-up compiles the environment (compileall): where PYTHONDONTWRITEBYTECODE is
    # set, a module without its .pyc is compiled again by every process that imports it
    import importlib.util
    if Path(sys.prefix).resolve() != (REPO / '.venv').resolve():
        pytest.skip('not run from the set-up environment (.venv)')
    missing = []
    for name in ('scipy.stats._stats_py', 'control.statefbk', 'rclpy.node', 'rosbags.rosbag2'):
        spec = importlib.util.find_spec(name)
        if not Path(importlib.util.cache_from_source(spec.origin)).is_file():
            missing.append(name)
    assert not missing, f'installed without their bytecode: {missing}'
