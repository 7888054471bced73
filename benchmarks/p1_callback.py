# benchmarks/p1_callback.py: P1's per-message work without DDS, one code version against another.
"""
CPU per message of the observer node's measurement callback, in process, per code version.

P1 (``p1_latency.py``) measures the whole DDS round trip, where this callback is about a
tenth of the time and the load of the machine moves the figures by more than a change of
the callback does. Here each version (a directory holding an ``observer_ros`` package:
a ``git archive`` of a commit) runs in its own process: it builds the ``ObserverNode`` of
``config/submarine.yaml`` in realtime mode (not spun: no timers, no subscribers) and calls
its ``_on_measurement`` with Imu messages stamped 4 ms apart (250 Hz, the P1 rate), in
the past of the clock. By default the stamps are offset by ``(i * 7919 % 1000)`` us, which
makes only two distinct steps (4.919 and 3.919 ms), each met again at once: the step
matrices and the gains come from the caches. ``--jitter-us J`` offsets each stamp by a
seeded uniform 0..J us instead, as the wall-clock stamps of P1's driver jitter (1st..99th
percentile of its steps 3.6-4.4 ms: ``--jitter-us 400``): nearly every step is new, and
costs its own matrix exponential and interpolated gain, as in the node. After a warm-up
of 500 messages (the first gains and 2 s of the envelope's learning), ``--reps`` blocks
of ``--count`` messages are timed with ``time.process_time``. The versions are
alternated, ``--rounds`` times. Printed per version: the smallest block (the least
disturbed by other processes) and the median, in microseconds of CPU per message.

Back to back, the callback runs with its code and data in the CPU's caches. The node
runs it once per message, and between two messages (4 ms at 250 Hz) the middleware's
threads and the other processes of the host run: ``--gap S`` sleeps S seconds before
each message and times each call alone (``time.thread_time``), which is what the node
pays per message (``--gap 0.004``: P1's period).

With ``--interleave`` the versions' processes run side by side, one block at a time in
turn (the others wait on a pipe, idle), the order rotated every block: each version's
blocks then meet the same load of the host, and each block of a version is paired with
the next version's. Also printed: the median and spread of the per-block ratios against
the first version (the figure a shared host moves least).

With ``--wire`` the messages are given as the subscriptions take them: a version whose
observer subscribes raw (``observer_ros/nodes/wire.py``) gets the serialized bytes, an
older one the message object, made from the same bytes by ``deserialize_message`` inside
the timed block (rclpy's take makes it before such a callback runs: that conversion is
part of the message's cost).

With ``--commands late`` each measurement is followed by the command answering the previous
estimate (P2's closed loop: stamped one step back, a rewind of the history each), with
``--commands inorder`` by the command answering this one; the figures are then per pair.
``--lag N`` makes the late command answer the estimate N messages back (P2's loop on a
loaded host: several steps late).

With ``--relay`` (and ``--wire``) each block is followed (or, every other block, preceded)
by the same messages through the bare relay of P1 (``relay_node.py``: each Imu taken as
rclpy's take makes it, then its callback publishes the JointState), in the same process,
under the same ``--gap``: printed as ``NAME:relay``, and the callback / relay per block,
the in-process counterpart of P1's CPU per message.

Usage: ``python benchmarks/p1_callback.py NAME=DIR [NAME=DIR ...] [--interleave]
[--commands late]``.

"""

import argparse
import os
from pathlib import Path
import statistics
import subprocess
import sys

DRIVER = """
import os, sys, time, warnings
warnings.filterwarnings('ignore')
import rclpy
from builtin_interfaces.msg import Time
from observer_ros.nodes.observer_node import ObserverNode
count, reps, config = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
sys.path.insert(0, sys.argv[4])    # benchmarks/ of this checkout: _common
from _common import gyro_imu
rclpy.init(args=['--ros-args', '--params-file', config, '-p', 'simulator.mode:=realtime',
                 '-r', '__ns:=/p1_callback'])
node = ObserverNode()
sensor = next(s for s in node.vehicle.sensors if s.topic.endswith('imu/data'))
msg = gyro_imu()
t0 = time.time_ns() - (500 + count * reps + 1000) * 4_000_000
commands = os.environ.get('P1_COMMANDS', 'none')
lag = int(os.environ.get('P1_LAG', '1'))
if commands != 'none':
    from sensor_msgs.msg import JointState
    cmd = JointState(name=list(node.vehicle.plant.input_names), position=[0.0])
jitter_ns = int(float(os.environ.get('P1_JITTER_US', '0')) * 1000)
gap = float(os.environ.get('P1_GAP', '0'))
if jitter_ns:
    import random
    rnd = random.Random(29)
    offsets = [rnd.randrange(jitter_ns + 1) for _ in range(500 + count * reps + 2)]
def stamp(i):
    ns = t0 + i * 4_000_000 + (offsets[i] if jitter_ns else (i * 7919 % 1000) * 1000)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
wire = os.environ.get('P1_WIRE') == '1'
if wire:    # as the subscriptions take them: bytes (raw), or the objects rclpy makes
    import importlib.util
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Imu, JointState
    raw_subs = importlib.util.find_spec('observer_ros.nodes.wire') is not None
def prepare(i):
    # the message i and its command (None): objects, or bytes with --wire
    msg.header.stamp = stamp(i)
    msg.angular_velocity.y = 0.001 * ((i % 200) - 100) / 100.0
    m = serialize_message(msg) if wire else msg
    c = None
    if commands != 'none':      # the closed loop's answer: to this estimate or the previous
        cmd.header.stamp = stamp(i - lag if commands == 'late' else i)
        cmd.position = [0.01 * ((i % 50) - 25) / 25.0]
        c = serialize_message(cmd) if wire else cmd
    return m, c
def one(item):
    m, c = item
    if wire and not raw_subs:   # the object rclpy's take would have made: timed too
        m = deserialize_message(m, Imu)
        c = None if c is None else deserialize_message(c, JointState)
    node._on_measurement(sensor, m)
    if c is not None:
        node._on_command(c)
relay = None
if os.environ.get('P1_RELAY') == '1':     # the bare relay's work on the same bytes
    from relay_node import Relay
    from sensor_msgs.msg import Imu
    from rclpy.serialization import deserialize_message
    relay = Relay()
    def relay_one(item):
        relay._on_imu(deserialize_message(item[0], Imu))   # as rclpy's take, then its callback
for i in range(500):
    one(prepare(i))
    if relay is not None:
        relay_one(prepare(i))
interleave = len(sys.argv) > 5
def timed(items, fn):
    # the CPU per message (us) of fn over items: back to back, or each after the gap
    if gap:     # each call alone, after the wait a node has between two messages
        spent = 0.0
        for item in items:
            time.sleep(gap)
            c0 = time.thread_time()
            fn(item)
            spent += time.thread_time() - c0
        return spent / len(items) * 1e6
    c0 = time.process_time()
    for item in items:
        fn(item)
    return (time.process_time() - c0) / len(items) * 1e6
for rep in range(reps):
    items = [prepare(i) for i in range(500 + rep * count, 500 + (rep + 1) * count)]
    if interleave:              # wait for our turn
        print('ready', flush=True)
        sys.stdin.readline()
    if relay is not None and rep % 2:   # the relay first every other block
        print('relay', timed(items, relay_one), flush=True)
    print(timed(items, one), flush=True)
    if relay is not None and not rep % 2:
        print('relay', timed(items, relay_one), flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""


def driver_command(directory, count, reps, commands='none', driver=DRIVER):
    """Return the environment and command line of a driver (``DRIVER``) on one version."""
    env = dict(os.environ, PYTHONPATH=str(directory), ROS_DOMAIN_ID='48', P1_COMMANDS=commands)
    config = Path(directory) / 'config' / 'submarine.yaml'
    bench = str(Path(__file__).resolve().parent)     # the driver's _common
    return env, [sys.executable, '-W', 'ignore', '-c', driver, str(count), str(reps),
                 str(config), bench]


def _blocks(directory, count, reps, commands, driver=DRIVER):
    """Run the driver on one version; return its blocks' CPU per message (us)."""
    env, argv = driver_command(directory, count, reps, commands, driver)
    out = subprocess.run(argv, env=env, cwd=str(directory),
                         capture_output=True, text=True, check=True).stdout
    return [float(line) for line in out.splitlines() if not line.startswith('relay')]


def _relay_blocks(directory, count, reps, commands, driver=DRIVER):
    """Run the driver with the bare relay beside the callback; return both blocks (us)."""
    env, argv = driver_command(directory, count, reps, commands, driver)
    env['P1_RELAY'] = '1'
    out = subprocess.run(argv, env=env, cwd=str(directory),
                         capture_output=True, text=True, check=True).stdout
    lines = out.splitlines()
    return ([float(line) for line in lines if not line.startswith('relay')],
            [float(line.split()[1]) for line in lines if line.startswith('relay')])


def _interleaved(versions, count, reps, commands, driver=DRIVER):
    """Run every version at once, a block at a time in turn; return their blocks (us)."""
    procs = []
    for _, directory in versions:
        env, argv = driver_command(directory, count, reps, commands, driver)
        procs.append(subprocess.Popen(argv + ['interleave'], env=env, cwd=str(directory),
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      stderr=subprocess.DEVNULL, text=True))
    blocks = [[] for _ in versions]
    try:
        for proc in procs:                      # every warm-up done
            _expect_ready(proc)
        for rep in range(reps):
            turn = rep % len(procs)
            for v in list(range(turn, len(procs))) + list(range(turn)):
                proc = procs[v]
                proc.stdin.write('go\n')
                proc.stdin.flush()
                blocks[v].append(float(proc.stdout.readline()))
                if rep + 1 < reps:
                    _expect_ready(proc)
    finally:
        for proc in procs:
            proc.stdin.close()
            proc.wait(timeout=60)
    return blocks


def _expect_ready(proc):
    line = proc.stdout.readline().strip()
    if line != 'ready':
        raise RuntimeError(f'driver said {line!r} instead of ready')


def version_parser(doc):
    """Return an argument parser of NAME=DIR versions, described by doc's first line."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[1])
    parser.add_argument('versions', nargs='+', metavar='NAME=DIR',
                        help='a name, and a directory holding an observer_ros package')
    return parser


def parse_versions(parser, argv):
    """
    Parse the command line of :func:`version_parser`; check its versions.

    Returns
    -------
    args : argparse.Namespace
        The arguments.
    versions : list of [name, directory], or None
        None after an ``error:`` line naming a version that is not NAME=DIR of an
        observer_ros package (the caller exits 2).

    """
    args = parser.parse_args(argv)
    versions = [v.split('=', 1) for v in args.versions]
    for version in versions:
        if len(version) != 2 or not (Path(version[1]) / 'observer_ros').is_dir():
            print(f'error: {"=".join(version)}: not NAME=DIR of an observer_ros package',
                  file=sys.stderr)
            return args, None
    return args, versions


def main(argv=None, driver=DRIVER, description=None):
    """Time ``driver`` (default: the observer's callback) on each version; print the blocks."""
    parser = version_parser(__doc__)
    if description:
        parser.description = description
    parser.add_argument('--count', type=int, default=1000, help='messages per block')
    parser.add_argument('--reps', type=int, default=15, help='blocks per run')
    parser.add_argument('--rounds', type=int, default=4, help='runs of each version')
    parser.add_argument('--interleave', action='store_true',
                        help='run the versions side by side, a block of each in turn')
    parser.add_argument('--commands', choices=('none', 'late', 'inorder'), default='none',
                        help="after each measurement, the compensator's command: stamped "
                        'like it (inorder) or like the previous one (late: the closed '
                        "loop's, one step late, a rewind of the history each); the figures "
                        'are then per measurement and command')
    parser.add_argument('--wire', action='store_true',
                        help='give the messages as the subscriptions take them: bytes to a '
                             'version with raw subscriptions, objects made from the bytes '
                             '(timed) to an older one')
    parser.add_argument('--jitter-us', type=float, default=0.0, metavar='J',
                        help='offset each stamp by a seeded uniform 0..J us (default: two '
                        "distinct steps; 400: the jitter of P1's wall-clock stamps)")
    parser.add_argument('--gap', type=float, default=0.0, metavar='S',
                        help='sleep S seconds before each message and time each call alone '
                        '(0.004: as the node runs it at 250 Hz; default: back to back)')
    parser.add_argument('--relay', action='store_true',
                        help="with --wire: also time benchmarks/relay_node.py's work on the "
                        'same bytes (take as an Imu object, its callback) in the same '
                        'process, block by block beside the callback; report callback / relay')
    parser.add_argument('--lag', type=int, default=1,
                        help='with --commands late: the command answers the estimate this '
                        'many messages back (default 1)')
    args, versions = parse_versions(parser, argv)
    if versions is None:
        return 2
    if args.relay and (not args.wire or args.interleave or args.commands != 'none'):
        print('error: --relay needs --wire, without --interleave or --commands',
              file=sys.stderr)
        return 2
    if args.lag < 1:
        print(f'error: --lag must be at least 1; got {args.lag}', file=sys.stderr)
        return 2
    os.environ['P1_LAG'] = str(args.lag)         # read by the drivers
    os.environ['P1_WIRE'] = '1' if args.wire else '0'
    os.environ['P1_JITTER_US'] = repr(args.jitter_us)
    os.environ['P1_GAP'] = repr(args.gap)
    print(f'load average at start: {os.getloadavg()[0]:.2f}')
    blocks = {name: [] for name, _ in versions}
    for r in range(args.rounds):
        if args.interleave:
            got_all = _interleaved(versions, args.count, args.reps, args.commands, driver)
            for (name, _), got in zip(versions, got_all):
                blocks[name] += got
                _print_round(r, name, got)
            continue
        for name, directory in (versions if r % 2 == 0 else versions[::-1]):
            if args.relay:
                got, relay = _relay_blocks(directory, args.count, args.reps, args.commands,
                                           driver)
                blocks.setdefault(f'{name}:relay', []).extend(relay)
                _print_round(r, f'{name}:relay', relay)
            else:
                got = _blocks(directory, args.count, args.reps, args.commands, driver)
            blocks[name] += got
            _print_round(r, name, got)
    first = versions[0][0]
    for name, got in blocks.items():
        print(f'CALLBACK {name}: min {min(got):.1f} us, median {statistics.median(got):.1f} us '
              f'of CPU per message ({len(got)} blocks of {args.count})')
        if args.relay and not name.endswith(':relay'):
            ratios = [a / b for a, b in zip(got, blocks[f'{name}:relay'])]
            print(f'  {name} / relay, block by block: median {statistics.median(ratios):.3f}'
                  f' [{min(ratios):.3f}..{max(ratios):.3f}]')
        if args.interleave and name != first:
            ratios = [a / b for a, b in zip(got, blocks[first])]
            print(f'  {name} / {first}, block by block: median {statistics.median(ratios):.3f}'
                  f' [{min(ratios):.3f}..{max(ratios):.3f}]')
    print(f'load average at end: {os.getloadavg()[0]:.2f}')
    return 0


def _print_round(r, name, got):
    print(f'  round {r + 1} {name:>10}: min {min(got):.1f} us, median '
          f'{statistics.median(got):.1f} us per message', flush=True)


if __name__ == '__main__':
    raise SystemExit(main())
