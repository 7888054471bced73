# The callback watch's decisions, on a fake node and clock (no ROS, no timing).
"""When to shed a flood, when to stop, when to leave the events executor, when to report."""

from types import SimpleNamespace

from diagnostic_msgs.msg import DiagnosticStatus
from observer_ros.nodes import callback_watch
from observer_ros.nodes.callback_watch import (BEAT, CallbackWatch, FLOOD_MESSAGES,
                                               LAG_LIMIT, LAG_RESUME)
import pytest


class _Node:
    """What the watch uses of a node: a wall timer, a name, topic names, a logger."""

    def __init__(self):
        self.logged = []

    def wall_timer(self, period, callback):
        return None

    def get_name(self):
        return 'observer'

    def resolve_topic_name(self, topic):
        return '/' + topic

    def get_logger(self):
        return SimpleNamespace(error=lambda text, **kw: self.logged.append(text))


def _watch(period=1.0):
    reports = []
    watch = CallbackWatch(_Node(), lambda *r: reports.append(r), lambda: period)
    watch._thread = object()            # no thread: the test calls _look itself
    sub = SimpleNamespace(raw=False)
    entry, callback = watch.guard('imu/data', lambda msg: taken.append(msg))
    entry.subscription = sub
    taken = []
    return watch, entry, callback, sub, taken, reports


def test_a_backlog_of_messages_is_shed_raw_until_the_heartbeat_is_back(monkeypatch):
    watch, entry, callback, sub, taken, _ = _watch()
    monkeypatch.setattr(callback_watch.time, 'monotonic', lambda: 100.0)
    watch._beat()
    for _ in range(FLOOD_MESSAGES):
        callback('m')
    watch._look(100.0 + LAG_LIMIT / 2)              # not late yet
    assert not watch.shedding and len(taken) == FLOOD_MESSAGES
    watch._look(100.0 + LAG_LIMIT + 0.01)           # late, messages still taken: a flood
    assert watch.shedding and sub.raw
    callback(b'raw bytes')                          # dropped, never handed on
    callback('a message taken before the switch')   # dropped too while shedding
    assert len(taken) == FLOOD_MESSAGES and entry.dropped == 2
    level, text = watch.status(100.6)
    # its rate from the messages taken since the heartbeat (none sampled in a second yet)
    assert level == DiagnosticStatus.ERROR and text.startswith(
        f'flooded: /imu/data at {FLOOD_MESSAGES / (LAG_LIMIT + 0.01):.0f} messages/s')
    monkeypatch.setattr(callback_watch.time, 'monotonic', lambda: 101.0)
    watch._beat()                                   # the queue drained
    watch._look(101.0 + LAG_RESUME / 2)
    assert not watch.shedding and not sub.raw
    callback(b'taken raw just before')              # a race at the switch: still dropped
    callback('m')
    assert taken[-1] == 'm' and entry.dropped == 3
    assert watch.values()['flood_dropped'] == 3 and watch.values()['flood_episodes'] == 1


def test_one_long_callback_is_not_a_flood_but_is_reported_on_time(monkeypatch):
    watch, _, callback, sub, taken, reports = _watch(period=1.0)
    monkeypatch.setattr(callback_watch.time, 'monotonic', lambda: 50.0)
    watch._beat()
    watch.status_at = 50.0
    callback('m')                                   # then a 3 s design step: no messages
    watch._look(50.0 + 1.0)
    assert not reports                              # the node's own report is not overdue
    watch._look(50.0 + 3.0)
    assert not watch.shedding and not sub.raw and taken == ['m']
    assert len(reports) == 1
    level, message, values = reports[0]
    assert level == DiagnosticStatus.ERROR and message.startswith(
        'late: no callback has run for 3.0 s') and \
        values['callback_lag_s'] == f'{3.0 - BEAT:.2f}'
    watch._look(50.0 + 3.5)                         # at most one report per period
    watch._look(50.0 + 4.1)
    assert len(reports) == 2


def test_a_flood_asks_to_leave_the_events_executor_at_once(monkeypatch):
    watch, _, callback, _, _, _ = _watch()
    monkeypatch.setattr(callback_watch.time, 'monotonic', lambda: 0.0)
    watch._beat()
    for _ in range(FLOOD_MESSAGES - 1):
        callback('m')
    watch._look(LAG_LIMIT + 0.01)                   # late, but too few messages: no flood
    assert not watch.shedding and not watch.overrun
    callback('m')
    watch._look(LAG_LIMIT + 0.02)
    assert watch.shedding and watch.overrun         # its queue grows even while shedding
    watch.overrun = watch.may_overrun = False       # what run_nodes does once it left
    watch._beat()
    watch._look(0.01)
    assert not watch.shedding
    for _ in range(FLOOD_MESSAGES):
        callback('m')
    watch._look(LAG_LIMIT + 0.01)                   # a second flood, in the wait-set executor
    assert watch.shedding and not watch.overrun


@pytest.mark.ros
def test_leaving_the_events_executor_keeps_every_node_spinning():
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.experimental import EventsExecutor
    from observer_ros.nodes.runner import _leave_events_executor
    from ros_helpers import DOMAIN_ID
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    node = rclpy.create_node('left', context=context)
    try:
        fired = []
        node.create_timer(0.01, lambda: fired.append(1))
        events = EventsExecutor(context=context)
        events.add_node(node)
        watch = SimpleNamespace(overrun=True, may_overrun=True)
        executor = _leave_events_executor(events, [node], [watch])
        assert isinstance(executor, SingleThreadedExecutor) and node in executor.get_nodes()
        assert not watch.overrun and not watch.may_overrun
        while not fired:
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
