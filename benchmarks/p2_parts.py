# benchmarks/p2_parts.py: P2's compensator share without DDS, one code version against another.
"""
CPU per estimate of the compensator node's estimate callback, in process, per code version.

P2 (``p2_closed_loop.py``) reports each process's CPU per simulator step, where about half
of the compensator's is the DDS publish and the machine's load moves the figure by more
than a change of the callback does. Here each version (a directory holding an
``observer_ros`` package: a ``git archive`` of a commit) builds the ``CompensatorNode`` of
``config/submarine.yaml`` in realtime mode, as P2 runs it (not spun: no timers, its
publisher without subscribers), and calls its ``_on_estimate`` with JointState estimates
stamped 1 ms apart (1 kHz, the P2 rate) with a few microseconds of jitter, moving inside
the divergence envelope. After a warm-up of 4000 estimates (the envelope's 3 s of
learning, so the timed blocks are the steady state), ``--reps`` blocks of ``--count``
estimates (built before each block) are timed with ``time.process_time``.

The versions are run, alternated and reported by ``p1_callback.py``'s machinery (the same
options: ``--rounds``, ``--interleave`` for the versions side by side, a block of each in
turn, with the per-block ratios against the first version; ``--wire``: the estimates as
the subscription takes them, bytes to a version that subscribes raw, objects made from the
bytes inside the timed block to an older one): only the driver differs.

Usage: ``python benchmarks/p2_parts.py NAME=DIR [NAME=DIR ...] [--interleave]``.

"""

from pathlib import Path
import sys

sys.path.insert(0, str(Path(__file__).resolve().parent))

import p1_callback  # noqa: E402

WARMUP = 4000       # estimates: more than the envelope's learning (3 s at 1 kHz)

DRIVER = """
import os, sys, time, warnings
warnings.filterwarnings('ignore')
import rclpy
from builtin_interfaces.msg import Time
from sensor_msgs.msg import JointState
from observer_ros.nodes.compensator import CompensatorNode
count, reps, config = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
rclpy.init(args=['--ros-args', '--params-file', config, '-p', 'simulator.mode:=realtime',
                 '-p', 'simulator.rate_hz:=1000.0', '-r', '__ns:=/p2_parts'])
node = CompensatorNode()
names = list(node.vehicle.plant.state_names)
WARMUP = %d
t0 = time.time_ns() - (WARMUP + count * reps + 1000) * 1_000_000
def estimate(i):
    ns = t0 + i * 1_000_000 + (i * 7919 %% 100) * 1000
    msg = JointState(name=names)
    msg.header.stamp = Time(sec=ns // 1_000_000_000, nanosec=ns %% 1_000_000_000)
    msg.position = [0.01 * (((i + 37 * k) %% 200) - 100) / 100.0 for k in range(len(names))]
    return msg
wire = os.environ.get('P1_WIRE') == '1'
take = lambda msg: msg
if wire:    # as the subscription takes them: bytes (raw), or the object rclpy makes (timed)
    import importlib.util
    from rclpy.serialization import deserialize_message, serialize_message
    if importlib.util.find_spec('observer_ros.nodes.wire') is None:
        take = lambda raw: deserialize_message(raw, JointState)
def prepared(i):
    msg = estimate(i)
    return serialize_message(msg) if wire else msg
for i in range(WARMUP):
    node._on_estimate(take(prepared(i)))
interleave = len(sys.argv) > 5
for rep in range(reps):
    block = [prepared(i) for i in range(WARMUP + rep * count, WARMUP + (rep + 1) * count)]
    if interleave:              # wait for our turn
        print('ready', flush=True)
        sys.stdin.readline()
    c0 = time.process_time()
    for msg in block:
        node._on_estimate(take(msg))
    print((time.process_time() - c0) / count * 1e6, flush=True)
node.destroy_node()
rclpy.try_shutdown()
""" % WARMUP


def main(argv=None):
    """Time the compensator's estimate callback on each version (p1_callback's options)."""
    return p1_callback.main(argv, driver=DRIVER, description=__doc__.splitlines()[1])


if __name__ == '__main__':
    raise SystemExit(main())
