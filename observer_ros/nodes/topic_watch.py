# observer_ros.nodes.topic_watch: publishers a subscription cannot hear (QoS, message type).
"""
Watch each subscription of a node for publishers whose messages never reach it.

DDS does not deliver a sample from a publisher whose QoS offer is incompatible with the
subscription's request (a best-effort publisher to a reliable subscription, a volatile one
to a transient-local subscription), nor from a publisher of another message type on the
same topic name; rclpy only logs the first. Each watched subscription gets rclpy's QoS
event callbacks (``incompatible_qos``, ``incompatible_type``: counted), and at every
diagnostics report the graph is asked who publishes on the topic, with which type and
which QoS (``get_publishers_info_by_topic``). A publisher of another type, or whose offer
``qos_check_compatible`` calls an error, is reported naming the topic, the publisher, what
it offers and what the subscription expects: ERROR when no publisher of the topic can be
heard, WARN when another one can.

"""

import time

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import qos_check_compatible, QoSCompatibility

__all__ = ['TopicWatch', 'type_name', 'describe_qos', 'level_rank']

# s: the graph is asked at most this often (a diagnostics report can come more often)
GRAPH_PERIOD = 0.5


def type_name(msg_class):
    """Return the ROS name of a message class: ``sensor_msgs/msg/Imu``."""
    return f'{msg_class.__module__.split(".", 1)[0]}/msg/{msg_class.__name__}'


def level_rank(level):
    """Return a DiagnosticStatus level (a byte in rclpy) as an int: OK 0 ... STALE 3."""
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def _policy(value):
    name = getattr(value, 'name', str(value))
    return name.lower()


def describe_qos(qos):
    """Return the policies that decide a match as text: ``reliability best_effort, ...``."""
    text = f'reliability {_policy(qos.reliability)}, durability {_policy(qos.durability)}'
    deadline = getattr(qos.deadline, 'nanoseconds', 0)
    if 0 < deadline < 2**63 - 1:        # a deadline is given (not 0, not infinite)
        text += f', deadline {deadline * 1e-9:g} s'
    return text


def _endpoint(info):
    ns = info.node_namespace.rstrip('/')
    return f'{ns}/{info.node_name}' if info.node_name else '(a publisher without a node)'


class TopicWatch:
    """
    The subscriptions of one node, and what keeps their publishers from being heard.

    Parameters
    ----------
    node : rclpy.node.Node
        The node (its graph is asked; its logger warns once per topic).

    """

    def __init__(self, node):
        self._node = node
        self._watched = []          # (subscription, resolved topic, expected type, qos)
        self._events = {}           # resolved topic -> {'incompatible_qos': n, ...}
        self._logged = set()
        self._checked_at = None
        self._problems = []

    def event_callbacks(self, topic):
        """Return the QoS event callbacks of a subscription to ``topic`` (as given)."""
        def on_qos(info, topic=topic):
            self._count(topic, 'incompatible_qos', info.total_count,
                        f'a publisher offers a QoS incompatible with this subscription '
                        f'(last policy: {_policy(info.last_policy_kind)})')

        def on_type(info, topic=topic):
            self._count(topic, 'incompatible_type', info.total_count,
                        'a publisher of another message type')
        return SubscriptionEventCallbacks(incompatible_qos=on_qos, incompatible_type=on_type)

    def _count(self, topic, key, total, text):
        resolved = self._node.resolve_topic_name(topic)
        self._events.setdefault(resolved, {})[key] = int(total)
        if (resolved, key) not in self._logged:
            self._logged.add((resolved, key))
            self._node.get_logger().warning(f'{resolved}: {text}: its messages are not '
                                            'received (see /diagnostics)')

    def add(self, subscription, msg_class, qos):
        """Watch a subscription made with :meth:`event_callbacks`."""
        self._watched.append((subscription, subscription.topic_name, type_name(msg_class),
                              qos))

    def forget(self, subscription):
        """Stop watching a subscription (destroyed: a managed node deactivated)."""
        self._watched = [w for w in self._watched if w[0] is not subscription]
        self._checked_at = None

    def problems(self, now=None):
        """
        Return ``(level, text)`` for each publisher that cannot be heard, worst first.

        The graph is asked at most every :data:`GRAPH_PERIOD` s; in between the last answer
        is returned.
        """
        now = time.monotonic() if now is None else now
        if self._checked_at is not None and now - self._checked_at < GRAPH_PERIOD:
            return self._problems
        self._checked_at = now
        found = []
        for sub, topic, expected, qos in self._watched:
            try:
                publishers = self._node.get_publishers_info_by_topic(topic)
            except Exception:   # noqa: BLE001 - a graph query failing says nothing of it
                continue
            bad, good = [], 0
            for info in publishers:
                if info.topic_type != expected:
                    bad.append(f'{topic}: {_endpoint(info)} publishes {info.topic_type}, '
                               f'this node expects {expected}')
                    continue
                verdict, reason = qos_check_compatible(info.qos_profile, qos)
                if verdict == QoSCompatibility.ERROR:
                    why = reason.replace('ERROR: ', '').rstrip(';')
                    bad.append(f'{topic}: {_endpoint(info)} offers '
                               f'{describe_qos(info.qos_profile)}; this node expects '
                               f'{describe_qos(qos)} ({why})')
                else:
                    good += 1
            level = DiagnosticStatus.WARN if good else DiagnosticStatus.ERROR
            for text in bad:
                found.append((level, f'{text}: its messages are not received'))
                key = (topic, text)
                if key not in self._logged:
                    self._logged.add(key)
                    self._node.get_logger().warning(f'{text}: its messages are not received')
        found.sort(key=lambda p: -level_rank(p[0]))
        self._problems = found
        return found

    def counters(self):
        """Return the QoS events counted per topic: ``{'incompatible_qos /t': n}``."""
        return {f'{key} {topic}': n for topic, keys in self._events.items()
                for key, n in keys.items()}
