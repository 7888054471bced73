# Shared fixtures of the suite, and the `ros` marker kept honest.
"""
Fixtures shared by the test folders: plants, vehicles, bags, node processes, hosts.

The helper modules beside this file (plants.py, bag_synth.py, bag_cases.py, ros_helpers.py,
netns.py) hold the functions; a test module takes fixtures from here and functions from
those, never from another test module.

A test that starts a process or a DDS participant carries the ``ros`` marker (pytest.ini):
``make check`` leaves those tests out. A test without the marker that starts either fails
at once, saying so. A ``ros`` test whose assertions depend on realtime scheduling (a
realtime closed loop, a latency, a rate) carries ``realtime`` as well: ``make test`` runs
those one at a time, after the others ran in workers; ``realtime`` alone implies ``ros``.
"""

import multiprocessing.process
from pathlib import Path
import resource
import subprocess

from bag_cases import make_case
from netns import two_hosts
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.vehicle import load_vehicle
import plants
import pytest
from ros_helpers import compensator_under_test, CONFIG, observer_under_test


def _refuse(what):
    def refuse(*args, **kwargs):
        raise RuntimeError(f'{what} in a test not marked ros: mark it @pytest.mark.ros')
    return refuse


# The modules holding the longest tests that start no process (CPU seconds per module in
# a make check run, 3 to 40 s), longest first. They run first, so that in pytest-xdist's
# workers no long test is left to start when the others are done (alphabetically the
# linters and the robust design's searches came last).
# Before them (make test only), the modules of the longest tests that start processes
# (single tests of 47 to 228 s in a run of make test's first stage at 1-minute load 12-17):
# one started last would hold its worker after the others are done. (xdist hands each
# worker two tests in a row at first: the two longest are not next to each other.)
LONGEST_FIRST = (
    'system/test_benchmarks_smoke.py', 'system/test_readme_commands.py',
    'evaluation/test_bag_batch_multihost.py', 'evaluation/test_bag_batch_workers.py',
    'tools/test_tools_robust.py', 'test_flake8.py', 'tuning/test_bag_tune_irregular.py',
    'replay/test_bag_replay_blocks.py', 'tuning/test_bag_tune_search.py',
    'evaluation/test_bag_eval.py', 'core/test_core_verify.py',
    'core/test_core_loop_supervisor.py', 'replay/test_bag_spill.py', 'tuning/test_bag_tune.py',
    'bag/test_bag_integrity.py', 'core/test_core_estimators.py', 'nodes/test_wire.py',
    'vehicle/test_vehicle.py', 'core/test_core_whiteness.py', 'test_pep257.py',
    'core/test_core_margins.py')


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """
    Mark every ``realtime`` test ``ros`` too, before ``-m`` selects (make check: not ros).

    The modules of LONGEST_FIRST go first, in its order; the others keep theirs.
    """
    for item in items:
        if item.get_closest_marker('realtime') and not item.get_closest_marker('ros'):
            item.add_marker(pytest.mark.ros)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    here = Path(__file__).parent

    def order(item):
        try:
            return rank.get(Path(item.fspath).relative_to(here).as_posix(), len(rank))
        except ValueError:
            return len(rank)
    items.sort(key=order)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Refuse processes and DDS participants in a test without the ``ros`` marker."""
    if item.get_closest_marker('ros') or item.get_closest_marker('linter'):
        yield
        return
    from rclpy.context import Context
    mp = pytest.MonkeyPatch()
    mp.setattr(subprocess.Popen, '__init__', _refuse('a process started'))
    mp.setattr(multiprocessing.process.BaseProcess, 'start', _refuse('a process started'))
    mp.setattr(Context, 'init', _refuse('a ROS context initialised'))
    try:
        yield
    finally:
        mp.undo()


# ------------------------------------------------------------------ CPU per test

def pytest_addoption(parser):
    """``--cpu-report N``: the N tests that took the most CPU, their processes' included."""
    parser.addoption('--cpu-report', type=int, default=0, metavar='N',
                     help='print the N tests with the most CPU seconds (the test process '
                          'and the processes it started and waited for)')


_CPU_AT_SETUP = pytest.StashKey()


def _cpu_seconds():
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    """Note the CPU used so far (``--cpu-report``), before the test's fixtures start."""
    if item.config.getoption('cpu_report'):
        item.stash[_CPU_AT_SETUP] = _cpu_seconds()
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """Count the CPU from the test's set-up to the end of its teardown (``--cpu-report``)."""
    yield
    start = item.stash.get(_CPU_AT_SETUP, None)
    if start is not None:
        own, children = _cpu_seconds()
        item.user_properties.append(('cpu_s', (own - start[0], children - start[1])))


def pytest_terminal_summary(terminalreporter, config):
    """
    Print ``--cpu-report``'s table: CPU s per module, and per test (its own, its processes').

    A test's figure runs from its set-up to the end of its teardown; a module-scoped
    fixture's are in its first and last test's. Processes count once waited for.
    """
    top = config.getoption('cpu_report')
    if not top:
        return
    rows = []
    for report in (r for reports in terminalreporter.stats.values() for r in reports):
        if getattr(report, 'when', None) != 'teardown':
            continue
        for key, value in report.user_properties:
            if key == 'cpu_s':
                rows.append((sum(value), value[0], value[1], report.nodeid))
    rows.sort(reverse=True)
    total = sum(r[0] for r in rows)
    write = terminalreporter.write_line
    write(f'CPU of the tests: {total:.0f} s ({sum(r[1] for r in rows):.0f} s in the '
          f'test processes, {sum(r[2] for r in rows):.0f} s in the processes they started)')
    by_module = {}
    for cpu, _, _, nodeid in rows:
        module = nodeid.split('::')[0]
        by_module[module] = by_module.get(module, 0.0) + cpu
    for module, cpu in sorted(by_module.items(), key=lambda kv: -kv[1])[:top]:
        write(f'{cpu:8.1f} s  {module}')
    for cpu, own, children, nodeid in rows[:top]:
        write(f'{cpu:8.1f} s  ({own:.1f} + {children:.1f} in processes)  {nodeid}')


# ------------------------------------------------------------------ plants and vehicles

@pytest.fixture
def submarine_plant():
    """Return the submarine (seed 000) with a rate gyro on q."""
    return plants.submarine()


@pytest.fixture
def two_sensor_plant():
    """Return the submarine with a gyro (q, output 0) and a pitch sensor (theta, output 1)."""
    return plants.two_sensor_submarine()


@pytest.fixture(scope='module')
def submarine_design():
    """Return config/submarine.yaml's vehicle and its design."""
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    return veh, design_vehicle(veh)


# ------------------------------------------------------------------ bags

@pytest.fixture(scope='module')
def cases(tmp_path_factory):
    """Return ``get(name)``: the vehicle and bag of a replay case (bag_cases.CASES), made once."""
    made = {}

    def get(name):
        if name not in made:
            made[name] = make_case(name, tmp_path_factory.mktemp(name))
        return made[name]
    return get


# ------------------------------------------------------------------ processes and hosts

@pytest.fixture
def observer_setup(tmp_path):
    """Run the observer node: its process, the probe, listener, gyro and command publishers."""
    with observer_under_test(tmp_path) as run:
        yield run.proc, run.probe, run.listener, run.pubs['imu/data'], run.pubs['control/u']


@pytest.fixture
def compensator_setup(tmp_path):
    """Run the compensator: its process, the probe, listener and estimate publisher."""
    with compensator_under_test(tmp_path) as run:
        yield run.proc, run.probe, run.listener, run.pubs['state/estimate']


@pytest.fixture
def hosts():
    """Two network namespaces joined by a veth pair (netns.py); skipped without root."""
    with two_hosts() as names:
        yield names
