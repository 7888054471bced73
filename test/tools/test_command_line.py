# Every executable's --help, and a node started without a usable params file.
"""--help on every executable; a missing or unparsable params file: one error line, exit 2."""

import subprocess
import sys

import pytest
from ros_helpers import CONFIG, ros_env

NODES = {'plant_simulator': 'observer_ros.nodes.plant_simulator',
         'observer': 'observer_ros.nodes.observer_node',
         'compensator': 'observer_ros.nodes.compensator',
         'recorder': 'observer_ros.nodes.recorder',
         'container': 'observer_ros.nodes.container'}
TOOLS = {'observer_design': 'observer_ros.tools.design_report',
         'observer_eval': 'observer_ros.evaluation.evaluate',
         'observer_tune': 'observer_ros.tuning.tune',
         'observer_play': 'observer_ros.bag.play',
         'observer_run': 'observer_ros.tools.run_closed_loop',
         'observer_bag_recover': 'observer_ros.bag.recover'}


def _run(module, *args):
    return subprocess.run([sys.executable, '-W', 'ignore::DeprecationWarning', '-m', module,
                           *args], capture_output=True, text=True, timeout=120,
                          env=ros_env())


def test_every_console_script_is_covered():
    text = (CONFIG.parent / 'setup.py').read_text()
    for name in list(NODES) + list(TOOLS):
        assert f"'{name} = " in text, name


@pytest.mark.ros
@pytest.mark.parametrize('name', sorted(NODES))
def test_node_help_gives_usage_params_file_and_topics(name):
    result = _run(NODES[name], '--help')
    assert result.returncode == 0, result.stderr
    assert 'usage:' in result.stdout and '--params-file' in result.stdout
    assert 'ros2 run observer_ros' in result.stdout
    # the topics: from the node's own description
    assert 'control/u' in result.stdout or 'observer' in result.stdout, result.stdout


@pytest.mark.ros
@pytest.mark.parametrize('name', sorted(TOOLS))
def test_tool_help(name):
    result = _run(TOOLS[name], '--help')
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith('usage:'), result.stdout


def _one_error(result):
    assert result.returncode == 2, result.stdout + result.stderr
    assert 'Traceback' not in result.stderr, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith('error:')]
    assert len(errors) == 1, result.stderr
    return errors[0]


@pytest.mark.ros
def test_node_without_params_file_says_how_to_start(tmp_path):
    line = _one_error(_run(NODES['observer']))
    assert '--params-file config/<vehicle>.yaml' in line


@pytest.mark.ros
def test_params_file_without_vehicle_sections_is_named(tmp_path):
    # a file ROS accepts (a scalar; parameters of another node) that holds no vehicle
    for name, text in (('scalar.yaml', '42\n'),
                       ('other.yaml', '/**:\n  ros__parameters:\n    foo: 1\n')):
        path = tmp_path / name
        path.write_text(text)
        line = _one_error(_run(NODES['observer'], '--ros-args', '--params-file', str(path)))
        assert f'no vehicle parameters in {path}' in line, line
        assert 'vehicle, model, sensors, observer, controller, simulator' in line, line


@pytest.mark.ros
def test_missing_params_file(tmp_path):
    line = _one_error(_run(NODES['observer'], '--ros-args', '--params-file',
                           str(tmp_path / 'nope.yaml')))
    assert 'nope.yaml' in line and 'No such file' in line


@pytest.mark.ros
def test_params_file_ros_refuses_is_one_line_not_a_traceback(tmp_path):
    # valid YAML for our loader, refused by ROS's parser (an array of mixed types)
    path = tmp_path / 'mixed.yaml'
    path.write_text('/**:\n  ros__parameters:\n    model:\n      A: [1.0, "x"]\n')
    line = _one_error(_run(NODES['compensator'], '--ros-args', '--params-file', str(path)))
    assert 'mixed.yaml' in line, line


@pytest.mark.ros
def test_observer_run_no_clock_turns_the_simulators_clock_off(monkeypatch, tmp_path, capsys):
    from observer_ros.core.errors import ObserverError
    from observer_ros.tools import run_closed_loop as tool
    seen = {}

    def fake_run(params_file, bag, **options):      # stands in for the four processes
        seen.update(options)
        raise ObserverError('stopped by the test')
    monkeypatch.setattr(tool, 'run_closed_loop', fake_run)
    code = tool.main([str(CONFIG / 'submarine.yaml'), '--namespace', 'sub2', '--no-clock',
                      '--out', str(tmp_path / 'bag')])
    assert code == 2 and 'stopped by the test' in capsys.readouterr().err
    assert seen['namespace'] == '/sub2'      # made absolute, as rcl needs it
    assert 'simulator.publish_clock:=false' in seen['overrides']


@pytest.mark.ros
@pytest.mark.parametrize('name', ['observer_design', 'observer_eval'])
def test_a_reader_that_left_ends_a_tool_quietly_and_its_outputs_stay(tmp_path, name):
    import os
    from observer_ros.core.errors import CLOSED_PIPE_STATUS
    read, write = os.pipe()
    os.close(read)          # `... | head` gone before the first line: every print fails
    out = tmp_path / 'eval'
    args = {'observer_design': [str(CONFIG / 'submarine.yaml')],
            'observer_eval': [str(CONFIG.parent / 'bags' / 'samples' / 'submarine'),
                              '--vehicle', str(CONFIG / 'submarine.yaml'), '--out', str(out),
                              '--no-plots', '--no-bag']}[name]
    try:
        done = subprocess.run([sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
                               TOOLS[name], *args], stdout=write, stderr=subprocess.PIPE,
                              text=True, timeout=300, env=ros_env())
    finally:
        os.close(write)
    # no BrokenPipeError traceback, no Python "Exception ignored ... <stdout>"
    assert done.returncode == CLOSED_PIPE_STATUS and done.stderr == '', done.stderr
    if name == 'observer_eval':
        assert sorted(p.name for p in out.iterdir()) == [
            '.observer_ros_output.json', 'results.csv', 'results.json', 'results.txt']
