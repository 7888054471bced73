# The package as a ROS 2 user meets it: colcon build, then the real `ros2` client.
"""The README's real-install commands, run with the real ros2 client and ros2 launch."""

import os
from pathlib import Path
import random
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time

import pytest
from ros_helpers import DOMAIN_ID, made_once, processes, REPO, RUN_SEED
import yaml

README = (REPO / 'README.md').read_text()
EXECUTABLES = ['compensator', 'container', 'observer', 'observer_bag_recover',
               'observer_design', 'observer_eval', 'observer_eval_batch', 'observer_play',
               'observer_run',
               'observer_tune', 'plant_simulator', 'recorder']
BUILD = 'colcon build --packages-select observer_ros'
LAUNCH = ('ros2 launch observer_ros closed_loop.launch.py vehicle:=submarine mode:=realtime '
          'duration:=0')
SECOND = LAUNCH + ' namespace:=sub2 publish_clock:=false'
MANAGED = LAUNCH + ' autostart:=false'
ECHO_STAMP = ('ros2 topic echo --once /state/estimate sensor_msgs/msg/JointState '
              '--field header.stamp')
LIFECYCLE = ('ros2 lifecycle get /observer', 'ros2 lifecycle set /observer configure',
             'ros2 lifecycle set /observer activate')
RESET = 'ros2 service call /observer/reset std_srvs/srv/Trigger'
# -w 1 publishes once the observer's subscription has matched; --keep-alive keeps the
# reliable publisher up until the observer has matched it too (DDS discovery is not
# symmetric: after the default 0.1 s the message can be lost on a loaded host)
SET_STATE = ('ros2 topic pub --once -w 1 --keep-alive 3 /observer/set_state '
             'sensor_msgs/msg/JointState "{name: [theta, w, q], position: [0.1, 0.0, 0.0]}"')
ROBOT = ('ros2 launch observer_ros observer.launch.py vehicle:=submarine '
         'remaps:="imu/data:=/robot/imu control/u:=/robot/cmd"')
RECORD = ('ros2 launch observer_ros closed_loop.launch.py vehicle:=pitch_imu mode:=lockstep '
          'record:=true bag:=bags/runs/pitch_launch')
WAIT = 180.0    # s: a loaded 2-core machine; every wait ends as soon as its condition holds


def _kit():
    """Return ../shared/ros2cli (the client's wheels) if it is there."""
    for parent in REPO.parents:
        kit = parent / 'shared' / 'ros2cli'
        if (kit / 'install.sh').is_file():
            return kit
    return None


def _client_setup():
    """Return the shell lines that put `ros2` on PATH, or skip when there is no client."""
    venv = Path(sys.prefix)
    kit = _kit()
    if kit is not None:
        if not (venv / 'bin' / 'ros2').exists():    # what `make setup` does
            subprocess.run([str(kit / 'install.sh'), str(venv)], check=True, timeout=600,
                           capture_output=True)
        return f'source {shlex.quote(str(kit / "env.sh"))} {shlex.quote(str(venv))}'
    if shutil.which('ros2'):
        return 'true'       # a real install: the user's sourced /opt/ros/jazzy
    pytest.skip('no ros2 client: ../shared/ros2cli is absent and no system ros2 is on PATH')


def _built_workspace(tmp_path_factory, setup):
    """
    Return a colcon workspace with the package built as the README says.

    One per test run (ros_helpers.made_once): every xdist worker runs its own commands in
    it, and no two write the same file.
    """
    def build(ws):
        (ws / 'src').mkdir()
        (ws / 'src' / 'observer_ros').symlink_to(REPO)
        result = subprocess.run(
            ['bash', '-c', f'{setup} && cd {shlex.quote(str(ws))} && {BUILD}'],
            env=dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID)), capture_output=True,
            timeout=600)
        assert result.returncode == 0, result.stderr.decode()[-3000:]
    return made_once(tmp_path_factory, 'ros2cli_ws', build)


@pytest.fixture(scope='module')
def ros2env(tmp_path_factory):
    """Build the package as the README says, in a workspace; return that shell's env."""
    setup = _client_setup()
    ws = _built_workspace(tmp_path_factory, setup)
    script = f'{setup} && cd {shlex.quote(str(ws))} && source install/setup.bash && env -0'
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1')
    result = subprocess.run(['bash', '-c', script], env=env, capture_output=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr.decode()[-3000:]
    env = dict(item.split('=', 1) for item in result.stdout.decode().split('\0') if '=' in item)
    env['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
    env['OBSERVER_ROS_WS'] = str(ws)
    yield env
    subprocess.run(['ros2', 'daemon', 'stop'], env=env, capture_output=True, timeout=60)


def _ros2(env, command, timeout=WAIT):
    """
    Run one ros2 command line (as typed in the README); return the CompletedProcess.

    On a timeout the command's whole process group is killed, not bash alone: a `ros2
    topic echo` left behind spun on for the rest of the suite.
    """
    proc = subprocess.Popen(['bash', '-c', command], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            cwd=env['OBSERVER_ROS_WS'])
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


class Launch:
    """A `ros2 launch` in its own process group: stop() is Ctrl-C in its terminal."""

    def __init__(self, env, command, log):
        self.log = log
        self._out = open(log, 'w')
        self.proc = subprocess.Popen(['bash', '-c', 'exec ' + command], env=env,
                                     stdout=self._out, stderr=subprocess.STDOUT,
                                     start_new_session=True, cwd=env['OBSERVER_ROS_WS'])

    def stop(self):
        """SIGINT to the whole group (as a terminal does); return the exit status."""
        _stop_group(self.proc)
        self._out.close()
        return self.proc.returncode

    def output(self):
        """Return what ros2 launch and its nodes printed."""
        if not self._out.closed:
            self._out.flush()
        return Path(self.log).read_text()


def _stop_group(proc):
    """SIGINT to a process group (Ctrl-C), SIGKILL after WAIT s; the group is gone after."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


# s: one try of a query that _ros2_until repeats (a client whose answer is lost, e.g. a
# `ros2 param set` on a loaded host, waits for good)
TRY = 60.0


def _ros2_until(env, command, done):
    """
    Run a ros2 command line until done(result) holds; return the last CompletedProcess.

    What ``ros2`` shows comes from DDS discovery, which on a loaded machine lags: the
    daemon lists a node before its endpoints (CI once saw ``ros2 node info`` print empty
    sections for a node ``ros2 node list`` already showed), and ``ros2 param`` gives up
    after its own 5 s wait for a node's parameter services. Every such query waits for
    what it is about, with the one deadline; the caller asserts on what came last. A try
    that has not ended after TRY s is stopped and made again, as a user would (every
    command repeated this way sets or reads the same values again).
    """
    deadline = time.monotonic() + WAIT
    while True:
        try:
            left = max(deadline - time.monotonic(), 1.0)
            result = _ros2(env, command, timeout=min(TRY, left))
            finished = done(result)
        except subprocess.TimeoutExpired as err:
            result = subprocess.CompletedProcess(command, None, '', f'{err}')
            finished = False
        if finished or time.monotonic() > deadline:
            return result


def _wait_nodes(env, *names):
    """Wait until `ros2 node list` shows every node (all started: Ctrl-C is safe)."""
    listed = _ros2_until(env, 'ros2 node list',
                         lambda r: set(names) <= set(r.stdout.split())).stdout.split()
    assert set(names) <= set(listed), f'nodes {names} not all up: {listed}'


def _section(info, name):
    """Return the lines of one section (Subscribers, Publishers, ...) of `ros2 node info`."""
    lines = info.splitlines()
    if f'  {name}:' not in lines:
        return ''
    section = []
    for line in lines[lines.index(f'  {name}:') + 1:]:
        if not line.startswith('    '):
            break
        section.append(line.strip())
    return '\n'.join(section)


def _node_endpoints(env, node, section, topic):
    """
    Return a section of `ros2 node info` once it lists `topic`, and the whole output.

    After the deadline, what was shown last (and ``ros2 node list``, for the message).
    """
    out = _ros2_until(env, f'ros2 node info {node}',
                      lambda r: f'{topic}:' in _section(r.stdout, section))
    shown = _section(out.stdout, section)
    if f'{topic}:' not in shown:
        listed = _ros2(env, 'ros2 node list -a')
        return shown, out.stdout + out.stderr + '\nros2 node list -a:\n' + listed.stdout
    return shown, out.stdout


def _ros2_param(env, command):
    """Run a `ros2 param` command line, again while the node's services are not found yet."""
    return _ros2_until(env, command, lambda r: 'Wait for service timed out' not in r.stderr
                       and 'Node not found' not in r.stdout + r.stderr)


def _assert_stopped_cleanly(launch, nodes, code=None):
    code = launch.stop() if code is None else code
    out = launch.output()
    assert code == 0, out[-3000:]
    assert 'process has died' not in out and 'Traceback' not in out, out[-3000:]
    assert out.count('process has finished cleanly') == nodes, out[-3000:]


def test_readme_commands_are_the_tested_ones():
    block = README[README.index('## On a real ROS 2 Jazzy install'):]
    block = block[:block.index('```', block.index('```') + 3)]
    for command in (BUILD, 'ros2 pkg executables observer_ros', LAUNCH, SECOND, ROBOT, RECORD,
                    'ros2 topic echo --once /state/estimate sensor_msgs/msg/JointState',
                    'ros2 param describe /observer model.A',
                    'ros2 param set /observer observer.poles "[-1.0, -1.1, -1.2]"',
                    'ros2 param dump /observer > observer.yaml && '
                    'ros2 param load /observer observer.yaml',
                    'ros2 run observer_ros observer --help'):
        assert command in block, command


@pytest.mark.ros
def test_each_executable_listed_once_and_runs(ros2env):
    result = _ros2(ros2env, 'ros2 pkg executables observer_ros')
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [w for exe in EXECUTABLES for w in ('observer_ros', exe)]
    result = _ros2(ros2env, 'ros2 run observer_ros observer --help')
    assert result.returncode == 0 and '--params-file' in result.stdout, result.stderr
    result = _ros2(ros2env, 'ros2 run observer_ros observer')   # no params file
    assert result.returncode == 2 and 'error: no vehicle parameters' in result.stderr


@pytest.mark.realtime
@pytest.mark.ros
def test_closed_loop_launch_params_and_one_clock(ros2env, tmp_path):
    first = Launch(ros2env, LAUNCH, tmp_path / 'first.log')
    second = None
    try:
        echo = _ros2(ros2env, 'ros2 topic echo --once /state/estimate sensor_msgs/msg/JointState')
        assert echo.returncode == 0 and 'position:' in echo.stdout, first.output()[-3000:]
        _check_current(ros2env)
        # a second vehicle that does not own time: still one /clock publisher
        second = Launch(ros2env, SECOND, tmp_path / 'second.log')
        echo = _ros2(ros2env,
                     'ros2 topic echo --once /sub2/state/estimate sensor_msgs/msg/JointState')
        assert echo.returncode == 0, second.output()[-3000:]
        _wait_nodes(ros2env, '/observer', '/compensator', '/plant_simulator',
                    '/sub2/observer', '/sub2/compensator', '/sub2/plant_simulator')
        # the second simulator's publishers are discovered, and /clock is not one of them
        second_sim, info = _node_endpoints(ros2env, '/sub2/plant_simulator', 'Publishers',
                                           '/sub2/imu/data')
        assert '/sub2/imu/data:' in second_sim and '/clock:' not in second_sim, info
        info = _ros2_until(ros2env, 'ros2 topic info /clock',
                           lambda r: re.search(r'Publisher count: [1-9]', r.stdout))
        assert 'Publisher count: 1' in info.stdout, info.stdout + first.output()[-2000:]
        _check_parameters(ros2env, tmp_path)
    finally:
        # stop both before judging either: a failed check must not leave a launch running
        codes = [first.stop()] + ([] if second is None else [second.stop()])
        for launch, code in zip((first, second), codes):
            _assert_stopped_cleanly(launch, 3, code)


def _seconds(echoed):
    """
    Return the time a `ros2 topic echo --once --field` of a Time printed, in s.

    Read from its `sec:` and `nanosec:` lines, not as YAML: a lost message's notice
    (`A message was lost!!!` and tab-indented counts) is not YAML.
    """
    sec = re.search(r'^sec: (\d+)$', echoed, re.M)
    nanosec = re.search(r'^nanosec: (\d+)$', echoed, re.M)
    assert sec and nanosec, echoed
    return int(sec.group(1)) + int(nanosec.group(1)) * 1e-9


def _check_current(env):
    """`ros2 topic echo --once` of an estimate shows one of now: within a period of /clock."""
    period = 1.0 / 20.0     # the submarine's simulator.rate_hz
    got = _ros2(env, f'ros2 topic echo --once /clock rosgraph_msgs/msg/Clock --field clock && '
                f'{ECHO_STAMP} && ros2 topic echo --once /clock rosgraph_msgs/msg/Clock '
                '--field clock')
    assert got.returncode == 0, got.stdout + got.stderr
    # echo prints a lost message's notice as a part of its own (ended by ---)
    parts = [part for part in got.stdout.split('---\n') if 'A message was lost' not in part]
    before, stamp, after = (_seconds(part) for part in parts[:3])
    assert before - period <= stamp <= after + period, (before, stamp, after)


def _check_parameters(env, tmp_path):
    describe = _ros2_param(env, 'ros2 param describe /observer model.A')
    assert 'Description: n x n, row-major' in describe.stdout, describe.stdout
    assert 'Read only: true' in describe.stdout, describe.stdout
    refused = _ros2_param(env, 'ros2 param set /observer model.A "[0.0]"')
    assert 'Trying to set a read-only parameter: model.A' in refused.stderr, refused
    refused = _ros2_param(env, 'ros2 param set /observer observer.poles "[0.5, -1.0, -2.0]"')
    said = refused.stdout + refused.stderr
    assert 'Setting parameter failed' in said and 'would not be stable' in said, said
    applied = _ros2_param(env, 'ros2 param set /observer observer.poles "[-1.0, -1.1, -1.2]"')
    assert applied.stdout.strip() == 'Set parameter successful', applied
    # dump, load, dump: the same values; only the read-only ones are reported as not set
    result = _ros2_param(env, 'ros2 param dump /observer > observer.yaml && '
                         'ros2 param load /observer observer.yaml')
    assert result.returncode == 0, result.stderr
    failed = [line for line in result.stderr.splitlines() if 'failed' in line]
    assert failed and all('read-only' in line for line in failed), result.stderr
    assert 'Set parameter observer.poles successful' in result.stdout, result.stdout
    dumped = Path(env['OBSERVER_ROS_WS']) / 'observer.yaml'
    again = _ros2_param(env, 'ros2 param dump /observer')
    assert yaml.safe_load(again.stdout) == yaml.safe_load(dumped.read_text())
    assert yaml.safe_load(again.stdout)['/observer']['ros__parameters']['observer'][
        'poles'] == [-1.0, -1.1, -1.2]


@pytest.mark.ros
def test_observer_launch_follows_the_remaps(ros2env, tmp_path):
    launch = Launch(ros2env, ROBOT, tmp_path / 'robot.log')
    pub = None
    try:
        pub = subprocess.Popen(
            ['ros2', 'topic', 'pub', '-r', '20', '/robot/imu', 'sensor_msgs/msg/Imu',
             '{header: {stamp: now}}'], env=ros2env, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, start_new_session=True)
        echo = _ros2(ros2env, 'ros2 topic echo --once /state/estimate sensor_msgs/msg/JointState')
        assert echo.returncode == 0 and 'position:' in echo.stdout, launch.output()[-3000:]
        _wait_nodes(ros2env, '/observer')
        subscribers, info = _node_endpoints(ros2env, '/observer', 'Subscribers', '/robot/imu')
        assert re.search(r'/robot/imu: sensor_msgs/msg/Imu', subscribers), info
        assert '/robot/cmd: sensor_msgs/msg/JointState' in subscribers, info
    finally:
        try:
            if pub is not None:
                _stop_group(pub)
        finally:
            _assert_stopped_cleanly(launch, 1)


@pytest.mark.ros
def test_recorded_lockstep_launch(ros2env, tmp_path):
    """The lock-step loop with the recorder: the run ends, and the launch with it."""
    launch = Launch(ros2env, RECORD, tmp_path / 'record.log')
    try:
        code = launch.proc.wait(timeout=WAIT)      # the simulator's run ends the launch
    finally:
        _assert_stopped_cleanly(launch, 4)
    out = launch.output()
    assert code == 0 and 'run complete at t=' in out, out[-3000:]
    assert 'process has finished cleanly' in out.split('run complete at t=')[1], out[-3000:]
    assert re.search(r'bag closed: bags/runs/pitch_launch \((\d+) messages\)', out), out
    bag = Path(ros2env['OBSERVER_ROS_WS']) / 'bags' / 'runs' / 'pitch_launch'
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in meta['topics_with_message_count']}
    # pitch_imu: 3 s at 500 Hz in lock-step, one true state per step (1501 with step 0)
    assert counts['/state/true'] >= 1500, counts
    # recorded on /clock's time (nothing at 0 s), by ROS 2 Jazzy
    assert meta['starting_time']['nanoseconds_since_epoch'] >= 1_000_000_000, meta
    assert meta['ros_distro'] == 'jazzy', meta


# Ctrl-C at a random moment: OBSERVER_ROS_SIGNAL_TRIES=50 is the on-demand bar
# (docs/reliability.md); test_shutdown.py does the same through observer-run.
SIGNAL_TRIES = int(os.environ.get('OBSERVER_ROS_SIGNAL_TRIES', '2'))
CLEAN_LAUNCH_NODES = 3


def _children(pid):
    """Return the pids of a process's children (from /proc)."""
    return [child for child, ppid, _ in processes() if ppid == pid]


def _handles_sigterm(pid):
    """Return True once a process has a handler for SIGTERM (a node's stop signals)."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return False
    caught = int(re.search(r'SigCgt:\s*([0-9a-f]+)', status).group(1), 16)
    return bool(caught & (1 << (signal.SIGTERM - 1)))


def _signal_moments(tries, seed):
    rng = random.Random(seed)
    return [('started' if i % 2 == 0 else 'running', rng.uniform(0.0, 3.0))
            for i in range(tries)]


@pytest.mark.ros
@pytest.mark.parametrize('phase, delay', _signal_moments(SIGNAL_TRIES, RUN_SEED))
def test_ctrl_c_at_a_random_moment_stops_every_node_cleanly(ros2env, tmp_path, phase, delay):
    """SIGINT to the launch's process group while the nodes start or while the loop runs."""
    launch = Launch(ros2env, LAUNCH, tmp_path / 'launch.log')
    try:
        deadline = time.monotonic() + WAIT
        while True:     # polling /proc and a log file, not timing anything
            assert launch.proc.poll() is None and time.monotonic() < deadline, \
                launch.output()[-3000:]
            if phase == 'started':
                kids = _children(launch.proc.pid)
                if len(kids) >= CLEAN_LAUNCH_NODES and all(map(_handles_sigterm, kids)):
                    break
            elif 'realtime run of' in launch.output():
                break
            time.sleep(0.05)
        time.sleep(delay)       # the random moment
    finally:
        _assert_stopped_cleanly(launch, CLEAN_LAUNCH_NODES)
    out = launch.output()
    assert 'FATAL' not in out and 'Exception in' not in out, out[-3000:]


@pytest.mark.ros
def test_managed_nodes_with_the_real_lifecycle_client(ros2env, tmp_path):
    """autostart:=false: the user brings the nodes up with `ros2 lifecycle set`."""
    launch = Launch(ros2env, MANAGED, tmp_path / 'managed.log')
    try:
        _wait_nodes(ros2env, '/observer', '/compensator')
        for node in ('/observer', '/compensator'):
            got = _ros2_until(ros2env, f'ros2 lifecycle get {node}',
                              lambda r: 'unconfigured' in r.stdout)
            assert got.stdout.strip() == 'unconfigured [1]', got.stdout + got.stderr
        # the simulator waits for both to be active
        assert 'plant_simulator' not in launch.output(), launch.output()[-3000:]
        refused = _ros2(ros2env, RESET)
        assert "success=False, message='not active (lifecycle state unconfigured)" in \
            refused.stdout, refused.stdout + refused.stderr
        for transition, state in (('configure', 'inactive [2]'), ('activate', 'active [3]')):
            for node in ('/observer', '/compensator'):
                done = _ros2(ros2env, f'ros2 lifecycle set {node} {transition}')
                assert done.stdout.strip() == 'Transitioning successful', \
                    done.stdout + done.stderr + launch.output()[-2000:]
                got = _ros2(ros2env, f'ros2 lifecycle get {node}')
                assert got.stdout.strip() == state, got.stdout + got.stderr
        echo = _ros2(ros2env, 'ros2 topic echo --once /state/estimate sensor_msgs/msg/JointState')
        assert echo.returncode == 0 and 'position:' in echo.stdout, launch.output()[-3000:]
        assert re.search(r'\[plant_simulator-\d+\]: process started', launch.output())
        # the reset service and the set_state topic, as robot_localization's set_pose
        done = _ros2(ros2env, RESET)
        said = "success=True, message='estimate reset to observer.initial_estimate [0.0, 0.0, 0.0]"
        assert said in done.stdout, done.stdout + done.stderr
        assert 'estimator reset on request (reset service)' in launch.output()
        done = _ros2(ros2env, SET_STATE)
        assert done.returncode == 0, done.stdout + done.stderr
        deadline = time.monotonic() + WAIT
        while 'set_state: state [0.1, 0.0, 0.0] at the next measurement' not in \
                launch.output():      # polling a log file, not timing anything
            assert time.monotonic() < deadline, launch.output()[-3000:]
            time.sleep(0.2)
        # deactivated, the compensator sends its safe command and stops commanding
        done = _ros2(ros2env, 'ros2 lifecycle set /compensator deactivate')
        assert done.stdout.strip() == 'Transitioning successful', done.stdout + done.stderr
        assert 'inactive: safe command sent (zero)' in launch.output(), launch.output()[-3000:]
        assert _ros2(ros2env, 'ros2 lifecycle get /compensator').stdout.strip() == \
            'inactive [2]'
        nodes = _ros2(ros2env, 'ros2 lifecycle nodes')
        assert {'/observer', '/compensator'} <= set(nodes.stdout.split()), nodes.stdout
    finally:
        _assert_stopped_cleanly(launch, 3)


@pytest.mark.ros
def test_a_vehicle_file_no_node_can_use_stops_the_launch(ros2env, tmp_path):
    """Checked before any node starts: one error naming the field, exit status 1."""
    bad = tmp_path / 'bad.yaml'
    bad.write_text((REPO / 'config' / 'submarine.yaml').read_text().replace(
        'C: [0.0, 0.0, 1.0]', 'C: [0.0, 1.0]'))
    result = _ros2(ros2env, f'ros2 launch observer_ros closed_loop.launch.py vehicle:={bad}')
    said = result.stdout + result.stderr
    assert result.returncode != 0 and 'model.C' in said, said[-3000:]
    assert 'process started' not in said, said[-3000:]
