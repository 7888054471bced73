# A measurement flood: /diagnostics keeps its period, memory stays bounded, the node recovers.
"""The observer under a 20 s flood of Imu (a process publishing as fast as it can)."""

import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticStatus
from observer_ros.timeutil import stamp_to_sec
import pytest
from ros_helpers import gyro_msg, observer_under_test, REALTIME, ros_env, rss_kib, WAIT

pytestmark = [pytest.mark.ros,       # processes or DDS participants
              pytest.mark.realtime]  # realtime closed loops or rates: one at a time

FLOOD = __file__.replace('test_nodes_flood.py', 'flood_publisher.py')
FLOOD_SECONDS = 20.0
PERIOD = 0.5
GYRO_PERIOD = 0.05          # the submarine's gyro: 20 Hz
# the bars: reports at most this far apart during the flood (s), the process's growth from
# before the flood to its end (KiB), `estimating` again this soon after the flood (s)
REPORT_GAP = 4 * PERIOD
RSS_GROWTH = 10 * 1024
RECOVERY = 5.0


def _statuses(listener):
    """Return (stamp, level, message, values) of each observer status heard so far."""
    out = []
    for array in listener.diagnostics:
        for status in array.status:
            if status.name.endswith('/observer'):
                out.append((stamp_to_sec(array.header.stamp), status.level, status.message,
                            {kv.key: kv.value for kv in status.values}))
    return out


class _Gyro:
    """The gyro at 20 Hz stamped on its slots (a late tick catches up), and the node's RSS."""

    def __init__(self, pub, pid):
        self.pub, self.pid = pub, pid
        self.slot = time.time_ns() // 50_000_000 * 50_000_000
        self.rss = []           # (wall s, KiB)
        self._rss_at = 0.0

    def tick(self):
        """Publish the messages due; sample the RSS every 0.25 s. Return False (a predicate)."""
        now = time.time_ns()
        while self.slot + 50_000_000 <= now:
            self.slot += 50_000_000
            self.pub.publish(gyro_msg(self.slot, 0.0))
        if now * 1e-9 - self._rss_at >= 0.25:
            self._rss_at = now * 1e-9
            self.rss.append((self._rss_at, rss_kib(self.pid)))
        return False


def test_a_flood_keeps_reports_on_time_memory_bounded_and_ends_in_estimating(tmp_path):
    params = (REALTIME, f'diagnostics_period:={PERIOD}')
    with observer_under_test(tmp_path, params=params) as run:
        gyro = _Gyro(run.pubs['imu/data'], run.proc.popen.pid)

        def until(predicate, what):
            run.probe.spin_until(lambda: gyro.tick() or predicate(), what=what)

        def latest():
            return _statuses(run.listener)[-1]
        until(lambda: latest()[1] == DiagnosticStatus.OK and latest()[2] == 'estimating',
              'estimating before the flood')
        rss_before = rss_kib(run.proc.popen.pid)
        flood = subprocess.Popen([sys.executable, '-W', 'ignore', FLOOD, 'imu/data',
                                  str(FLOOD_SECONDS)],
                                 stdout=subprocess.PIPE, text=True, env=ros_env())
        try:
            until(lambda: any(s[1] == DiagnosticStatus.ERROR and 'flooded: /imu/data' in s[2]
                              for s in _statuses(run.listener)), 'the flood reported')
            until(lambda: flood.poll() is not None, 'the flood to end')
            flood_end = time.time()
            out = flood.stdout.read().strip()
        finally:
            if flood.poll() is None:
                flood.kill()
            flood.wait(timeout=WAIT)
        # after the flood: `estimating` again, and it stays so
        until(lambda: any(s[0] > flood_end and s[2] == 'estimating'
                          for s in _statuses(run.listener)), 'estimating after the flood')
        back = next(s[0] for s in _statuses(run.listener)
                    if s[0] > flood_end and s[2] == 'estimating')
        until(lambda: latest()[0] > back + 4 * PERIOD, 'reports after recovery')
        after = [s for s in _statuses(run.listener) if s[0] >= back]
        statuses = _statuses(run.listener)
    start = flood_end - FLOOD_SECONDS
    during = [s for s in statuses if start <= s[0] <= flood_end]
    gaps = [b[0] - a[0] for a, b in zip(during, during[1:])]
    growth = max(k for t, k in gyro.rss if t <= flood_end) - rss_before
    print(f'{out}; {len(during)} reports during the flood, largest gap {max(gaps):.2f} s; '
          f'RSS +{growth} KiB; estimating {back - flood_end:.2f} s after the flood')
    # /diagnostics kept its period: the node's timer or its watch's thread
    assert max(gaps) <= REPORT_GAP, gaps
    assert growth <= RSS_GROWTH, gyro.rss
    assert back - flood_end <= RECOVERY
    assert all(s[2] == 'estimating' for s in after), [s[2] for s in after]
    values = during[-1][3]
    assert int(values['flood_episodes']) >= 1 and 'flood_dropped' in values
