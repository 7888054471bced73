# The ranges `ros2 param describe` shows are the schema's (the real Jazzy client).
"""
What the real ``ros2 param describe`` prints for every bounded parameter equals the schema.

The three nodes run in one process (the container) on a submarine file that gives every
bounded vehicle key; the nodes declare their own parameters with their defaults. The
client is the real ros2cli from ../shared/ros2cli (or a sourced Jazzy install).
"""

import os
from pathlib import Path
import re
import shlex
import shutil
import subprocess
import sys
import time

from observer_ros.vehicle import load_parameters, parameters_to_yaml
from observer_ros.vehicle.schema import interval_text, known_keys, NODE_KEYS, ros_range
import pytest
from ros_helpers import DOMAIN_ID, python, REPO, SUBMARINE, WAIT

pytestmark = pytest.mark.ros      # processes or DDS participants

NODES = {
    'observer': ('clock_jump_tolerance', 'future_tolerance', 'diagnostics_period'),
    'compensator': ('clock_jump_tolerance', 'diagnostics_period', 'command_lead_steps'),
    'plant_simulator': ('start_time', 'wait_for_subscribers', 'diagnostics_period'),
}
# every bounded vehicle key, at a value the submarine accepts
EXTRA = {'observer.rate_hz': 20.0, 'observer.publish_rate_hz': 10.0,
         'observer.history_length': 0.25, 'controller.stale_timeout': 0.5,
         'controller.predict_timeout': 0.0, 'simulator.mode': 'realtime',
         'simulator.duration': 0.0, 'simulator.realtime_factor': 1.0,
         'simulator.command_timeout': 2.0, 'simulator.seed': 0,
         'sensors.gyro.timeout': 0.5, 'sensors.gyro.rate_divider': 1}


def _client():
    """Return the shell line that puts the real `ros2` on PATH, or skip."""
    venv = Path(sys.prefix)
    for parent in REPO.parents:
        kit = parent / 'shared' / 'ros2cli'
        if (kit / 'env.sh').is_file():
            if not (venv / 'bin' / 'ros2').exists():     # what `make setup` does
                subprocess.run([str(kit / 'install.sh'), str(venv)], check=True,
                               capture_output=True, timeout=600)
            return f'source {shlex.quote(str(kit / "env.sh"))} {shlex.quote(str(venv))}'
    if shutil.which('ros2'):
        return 'true'
    pytest.skip('no ros2 client: ../shared/ros2cli is absent and no system ros2 is on PATH')


def _ros2(setup, command, done):
    """Run a ros2 command line until done(output) holds (discovery lags); return output."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID))
    deadline = time.monotonic() + WAIT
    while True:
        result = subprocess.run(['bash', '-c', f'{setup} && {command}'], env=env, text=True,
                                capture_output=True, timeout=WAIT)
        out = result.stdout + result.stderr
        if done(out) or time.monotonic() > deadline:
            return out


def _described(text):
    """Return {name: {field: value}} from `ros2 param describe` output."""
    found, current = {}, None
    for line in text.splitlines():
        key, _, value = line.strip().partition(': ')
        if key == 'Parameter name':
            current = found.setdefault(value, {})
        elif current is not None and key in ('Min value', 'Max value',
                                             'Additional constraints', 'Read only'):
            current[key] = value
    return found


@pytest.fixture(scope='module')
def nodes(tmp_path_factory):
    """Run the three nodes in one container; yield the client's set-up line and the file."""
    setup = _client()
    tmp = tmp_path_factory.mktemp('ranges')
    flat = load_parameters(SUBMARINE)
    flat.update(EXTRA)
    params = tmp / 'vehicle.yaml'
    params.write_text(parameters_to_yaml(flat))
    log = open(tmp / 'container.log', 'w')
    proc = subprocess.Popen([python(), '-m', 'observer_ros.nodes.container', *NODES,
                             '--ros-args', '--params-file', str(params)],
                            env=dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID)),
                            stdout=log, stderr=subprocess.STDOUT)
    try:
        yield setup, flat
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def _number(text):
    return int(text) if re.fullmatch(r'-?\d+', text) else float(text)


@pytest.mark.parametrize('node', list(NODES))
def test_describe_shows_the_schemas_ranges(nodes, node):
    setup, flat = nodes
    schema = dict(known_keys(['gyro']))
    names = [n for n in flat if n in schema and ros_range(schema[n]) is not None]
    names += list(NODES[node])
    schema.update(NODE_KEYS)
    command = (f'ros2 param describe --no-daemon --spin-time 5 /{node} ' +
               ' '.join(names) + ' model.A sensors.gyro.noise_std')
    out = _ros2(setup, command, lambda text: 'Parameter name: model.A' in text)
    described = _described(out)
    assert set(names) | {'model.A', 'sensors.gyro.noise_std'} <= set(described), out
    for name in names:
        spec, shown = schema[name], described[name]
        assert (_number(shown['Min value']), _number(shown['Max value'])) == \
            ros_range(spec), (name, shown)
        assert shown['Additional constraints'].startswith(interval_text(spec)), (name, shown)
    # open bounds (> 0) as ROS holds them; the "Min value: 0.0" for "> 0" is gone
    if node == 'observer':
        assert described['future_tolerance']['Min value'] == '5e-324'
        assert described['simulator.rate_hz']['Min value'] == '0.001'
        assert described['simulator.rate_hz']['Max value'] == '10000.0'
        assert described['diagnostics_period']['Min value'] == '0.01'
    # no range where the schema has none; an array's bound in words
    assert 'Min value' not in described['model.A'], out
    assert described['sensors.gyro.noise_std'] == {'Read only': 'true',
                                                   'Additional constraints': 'each >= 0'}


def test_set_a_key_the_file_did_not_give_and_refusals_name_the_key(nodes):
    setup, _ = nodes
    ok = _ros2(setup, 'ros2 param set --no-daemon /compensator controller.reference '
               '"[0.1, 0.0, 0.0]"', lambda text: 'Set parameter' in text)
    assert 'Set parameter successful' in ok, ok
    bogus = _ros2(setup, 'ros2 param set --no-daemon /observer observer.bogus 1.0',
                  lambda text: 'Setting parameter failed' in text)
    assert 'observer.bogus: not a parameter of /observer' in bogus, bogus
    huge = _ros2(setup, 'ros2 param set --no-daemon /observer observer.initial_estimate '
                 '"[1.0e+308, 0.0, 0.0]"', lambda text: 'Setting parameter failed' in text)
    assert 'observer.initial_estimate: element 0: 1e+308 is outside [-1e+09, 1e+09]' in huge
    fast = _ros2(setup, 'ros2 param set --no-daemon /observer future_tolerance 0.0',
                 lambda text: 'Setting parameter failed' in text)
    assert 'out of range' in fast, fast
