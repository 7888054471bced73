# Reading parameters files: what ROS's parser accepts and nothing more, within limits.
"""The loader refuses aliases, oversized files, over-long arrays and non-UTF-8 text."""

import os
import signal
import subprocess
import sys
import time

from observer_ros import params_file
from observer_ros.core.errors import VehicleFileError
from observer_ros.params_file import (MAX_ARRAY_LENGTH, MAX_FILE_BYTES, MAX_NESTING,
                                      regular_file, STREAM_TIMEOUT)
from observer_ros.vehicle import load_parameters, load_vehicle
import pytest
from ros_helpers import CONFIG, ros_env, WAIT

HEAD = '/**:\n  ros__parameters:\n'
SAMPLE = CONFIG.parent / 'bags' / 'samples' / 'submarine'


def _alias_bomb(path):
    lines = [HEAD + '    a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 10):
        name, prev = chr(97 + i), chr(96 + i)
        lines.append(f'    {name}: &{name} [' + ', '.join([f'*{prev}'] * 9) + ']')
    path.write_text('\n'.join(lines) + '\n')
    return path


def _long_array(path, n):
    path.write_text(HEAD + '    model:\n      A: [' + ', '.join(['1.0'] * n) + ']\n')
    return path


def test_aliases_are_refused_as_ros_does(tmp_path):
    start = time.monotonic()
    with pytest.raises(VehicleFileError, match=r'anchors and aliases .* not allowed'):
        load_parameters(_alias_bomb(tmp_path / 'bomb.yaml'))
    assert time.monotonic() - start < 5.0       # refused at the first anchor, not expanded
    # a lone anchor too: ROS refuses the file
    (tmp_path / 'anchor.yaml').write_text(HEAD + '    a: &x 1.0\n')
    with pytest.raises(VehicleFileError, match='line 3'):
        load_parameters(tmp_path / 'anchor.yaml')


def test_file_size_is_checked_before_reading(tmp_path):
    path = tmp_path / 'big.yaml'
    with open(path, 'w') as f:
        f.write(HEAD + '    # ' + 'x' * (50 * MAX_FILE_BYTES) + '\n')
    with pytest.raises(VehicleFileError) as err:
        load_parameters(path)
    assert 'MAX_FILE_BYTES' in str(err.value) and str(MAX_FILE_BYTES) in str(err.value)
    assert '\n' not in str(err.value)


def test_array_length_is_limited(tmp_path):
    with pytest.raises(VehicleFileError) as err:
        load_parameters(_long_array(tmp_path / 'long.yaml', MAX_ARRAY_LENGTH + 1))
    assert 'MAX_ARRAY_LENGTH' in str(err.value) and '\n' not in str(err.value)
    # at the limit: read
    flat = load_parameters(_long_array(tmp_path / 'ok.yaml', MAX_ARRAY_LENGTH))
    assert len(flat['model.A']) == MAX_ARRAY_LENGTH


@pytest.mark.parametrize('deep', [' {a: ' * 30000 + '1' + '}' * 30000,
                                  ''.join(f'\n{"  " * (i + 4)}a:' for i in range(60)) + ' 1',
                                  ' ' + '[' * 60 + ']' * 60])
def test_deep_nesting_is_one_clear_error(tmp_path, deep):
    # {a: {a: ...}} 30000 deep: one error naming the file, not a RecursionError traceback
    path = tmp_path / 'deep.yaml'
    path.write_text(HEAD + '    vehicle:\n      name:' + deep + '\n')
    with pytest.raises(VehicleFileError, match=r'deep.yaml: not valid YAML: nested more '
                       f'than {MAX_NESTING} levels deep \\(MAX_NESTING\\)') as err:
        load_parameters(path)
    assert '\n' not in str(err.value)


def test_non_utf8_is_one_clear_error(tmp_path):
    path = tmp_path / 'latin1.yaml'
    path.write_bytes(HEAD.encode() + b'    vehicle:\n      name: caf\xe9\n')
    with pytest.raises(VehicleFileError, match=r'not UTF-8 .*0xe9.*line 4'):
        load_parameters(path)


def test_every_shipped_vehicle_is_within_the_limits():
    for path in CONFIG.glob('*.yaml'):
        assert path.stat().st_size < MAX_FILE_BYTES / 10, path
        load_vehicle(path)


def _run(module, *args):
    start = time.monotonic()
    result = subprocess.run([sys.executable, '-W', 'ignore::DeprecationWarning', '-m', module,
                             *args], capture_output=True, text=True, timeout=120,
                            env=ros_env())
    return result, time.monotonic() - start


@pytest.mark.ros
@pytest.mark.parametrize('make', ['bomb', 'big', 'long'])
def test_node_refuses_a_file_as_the_tool_does(tmp_path, make):
    path = tmp_path / f'{make}.yaml'
    if make == 'bomb':
        _alias_bomb(path)
    elif make == 'long':
        _long_array(path, MAX_ARRAY_LENGTH + 1)
    else:
        path.write_text(HEAD + '    # ' + 'x' * (2 * MAX_FILE_BYTES) + '\n')
    tool, tool_s = _run('observer_ros.tools.design_report', str(path))
    node, node_s = _run('observer_ros.nodes.observer_node', '--ros-args', '--params-file',
                        str(path))
    for result in (tool, node):
        assert result.returncode == 2, result.stderr
        errors = [line for line in result.stderr.splitlines() if line.startswith('error:')]
        assert len(errors) == 1 and 'Traceback' not in result.stderr, result.stderr
    # the same refusal, before rclpy parses the file
    assert tool.stderr.strip().splitlines()[-1] == node.stderr.strip().splitlines()[-1]
    assert node_s < 30.0, node_s


def _fifo(tmp_path):
    path = tmp_path / 'v.yaml'
    os.mkfifo(path)
    return path


def test_a_fifo_without_a_writer_is_refused_not_waited_on(tmp_path, monkeypatch):
    assert STREAM_TIMEOUT == 5.0
    # the wait shortened for the test (the rule is the same at any length)
    monkeypatch.setattr(params_file, 'STREAM_TIMEOUT', 0.25)
    path = _fifo(tmp_path)
    start = time.monotonic()
    with pytest.raises(VehicleFileError, match=r'a pipe, and no writer gave it any text '
                       r'within 0.25 s \(STREAM_TIMEOUT\)'):
        load_parameters(path)
    waited = time.monotonic() - start
    assert 0.25 <= waited < 0.25 + 30.0                   # bounded, not forever


@pytest.mark.ros
def test_a_pipe_with_a_writer_is_read_once_and_copied_for_rclpy(tmp_path):
    path = _fifo(tmp_path)
    writer = subprocess.Popen(['sh', '-c', f'cat "{CONFIG / "submarine.yaml"}" > "{path}"'])
    try:
        vehicle = load_vehicle(path)
        assert vehicle.name == 'submarine'
        # read again in the same process (observer-run loads it three times): the same text
        assert load_vehicle(path).name == 'submarine'
        copy = regular_file(path)
        assert copy != path and os.path.isfile(copy)
        assert open(copy).read() == (CONFIG / 'submarine.yaml').read_text()
        assert regular_file(CONFIG / 'submarine.yaml') == CONFIG / 'submarine.yaml'
    finally:
        writer.wait(timeout=WAIT)


@pytest.mark.parametrize('path, kind', [('/dev/zero', 'a character device'),
                                        ('/dev/null', 'a character device'),
                                        ('.', 'a folder')])
def test_devices_and_folders_are_refused_unopened(path, kind):
    with pytest.raises(VehicleFileError, match=f'{kind}, not a parameters file'):
        load_parameters(path)


@pytest.mark.ros
@pytest.mark.parametrize('entry', [
    ['observer_ros.tools.design_report', '{}'],
    ['observer_ros.evaluation.evaluate', str(SAMPLE), '--vehicle', '{}'],
    ['observer_ros.tuning.tune', str(SAMPLE), '--vehicle', '{}'],
    ['observer_ros.tools.run_closed_loop', '{}'],
    ['observer_ros.nodes.observer_node', '--ros-args', '--params-file', '{}'],
    ['observer_ros.nodes.container', 'observer', 'compensator', '--ros-args',
     '--params-file', '{}'],
])
def test_every_entry_point_refuses_a_fifo_without_a_writer_in_one_line(tmp_path, entry):
    path = _fifo(tmp_path)
    result, _ = _run(entry[0], *[a.format(path) for a in entry[1:]])
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith('error:')]
    assert len(errors) == 1 and 'Traceback' not in result.stderr, result.stderr
    assert 'a pipe, and no writer gave it any text' in errors[0], result.stderr


@pytest.mark.ros
def test_process_substitution_works_for_a_tool_and_a_node(tmp_path):
    vehicle = CONFIG / 'submarine.yaml'
    tool = subprocess.run(['bash', '-c', f'"{sys.executable}" -W ignore -m '
                           f'observer_ros.tools.design_report <(cat "{vehicle}")'],
                          capture_output=True, text=True, timeout=120, env=ros_env())
    assert tool.returncode == 0, tool.stderr
    assert 'Vehicle: submarine' in tool.stdout
    # the node reads the pipe for its check, rclpy a copy: it starts (and says so)
    node = subprocess.Popen(['bash', '-c', f'exec "{sys.executable}" -W ignore -m '
                             f'observer_ros.nodes.observer_node --ros-args --params-file '
                             f'<(cat "{vehicle}") -p simulator.mode:=realtime'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=ros_env())
    try:
        for line in node.stdout:
            if 'submarine: observer full' in line:
                break
        else:
            pytest.fail('the node did not start')
    finally:
        node.send_signal(signal.SIGINT)
        assert node.wait(timeout=WAIT) == 0


@pytest.mark.ros
def test_a_compare_file_may_be_a_pipe_and_a_fifo_without_a_writer_is_named_as_one(tmp_path):
    from observer_ros.evaluation.evaluator import parse_compare
    from observer_ros.core.errors import ObserverError
    path = _fifo(tmp_path)
    # it exists: not "no such file" (before), but what it is, once it is read
    assert parse_compare(f'tuned={path}') == ('tuned', str(path))
    writer = subprocess.Popen(['sh', '-c', f'cat "{CONFIG / "submarine.yaml"}" > "{path}"'])
    try:
        assert load_vehicle(path).name == 'submarine'
    finally:
        writer.wait(timeout=WAIT)
    with pytest.raises(ObserverError, match='--compare .*: no such file'):
        parse_compare(str(tmp_path / 'missing.yaml'))
    result, _ = _run('observer_ros.evaluation.evaluate', str(SAMPLE), '--vehicle',
                     str(CONFIG / 'submarine.yaml'), '--compare', str(tmp_path),
                     '--out', str(tmp_path / 'eval'))
    assert result.returncode == 2 and result.stderr.strip().splitlines() == [
        f'error: {tmp_path}: a folder, not a parameters file (a regular file, or a pipe with '
        'a writer)'], result.stderr
    assert not (tmp_path / 'eval').exists()
