# A measurement flood: /diagnostics keeps coming, the flood is named, the node recovers.
"""The observer under a flood of Imu (a process publishing as fast as it can)."""

import subprocess
import sys

from diagnostic_msgs.msg import DiagnosticStatus
from observer_ros.timeutil import stamp_to_sec
import pytest
from ros_helpers import COMMANDS, observer_under_test, REALTIME, ros_env, WAIT

pytestmark = pytest.mark.ros      # processes or DDS participants

FLOOD = __file__.replace('test_nodes_flood.py', 'flood_publisher.py')
PERIOD = 0.5


def _statuses(listener):
    """Return (stamp, level, message, values) of each observer status heard so far."""
    out = []
    for array in listener.diagnostics:
        for status in array.status:
            if status.name.endswith('/observer'):
                out.append((stamp_to_sec(array.header.stamp), status.level, status.message,
                            {kv.key: kv.value for kv in status.values}))
    return out


def test_a_flood_is_named_and_diagnostics_keep_coming(tmp_path):
    params = (REALTIME, f'diagnostics_period:={PERIOD}')
    with observer_under_test(tmp_path, publish=(COMMANDS,), params=params) as run:
        heard_before = len(run.listener.diagnostics)
        flood = subprocess.Popen([sys.executable, '-W', 'ignore', FLOOD, 'imu/data', '8'],
                                 stdout=subprocess.PIPE, text=True, env=ros_env())
        try:
            run.probe.spin_until(lambda: any(s[1] == DiagnosticStatus.ERROR and
                                             s[2].startswith(('flooded: /imu/data',
                                                              'late: flooded: /imu/data'))
                                             for s in _statuses(run.listener)),
                                 what='the flood reported')
            run.probe.spin_until(lambda: flood.poll() is not None, what='the flood to end')
            out = flood.stdout.read()
        finally:
            if flood.poll() is None:
                flood.kill()
            flood.wait(timeout=WAIT)
        run.listener.wait_counter('observer', 'flood_dropped', 1)
        # after the flood: the observer takes messages again, and says it is fine
        run.probe.spin_until(lambda: not _statuses(run.listener)[-1][2].startswith(
            ('flooded', 'late')), what='the flood no longer reported')
        during = _statuses(run.listener)[heard_before:]
        stamps = [s[0] for s in during]
        gaps = [b - a for a, b in zip(stamps, stamps[1:])]
        print(out, f'{len(during)} reports, largest gap {max(gaps):.2f} s')
        # reports kept coming (the node's timer or its watch's thread): before, none came
        # for 5 to 8 periods of 1 s while the executor worked through its queue
        assert max(gaps) < 8 * PERIOD, gaps
        values = during[-1][3]
        assert int(values['flood_episodes']) >= 1 and int(values['flood_dropped']) > 0
