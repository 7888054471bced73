# observer_ros.bag.play: `observer-play BAG`: publish a bag's messages with their timing.
"""
Play a bag: publish its recorded (serialized) messages with the recorded timing.

Like ``ros2 bag play --clock``, without ros2bag: the bag is read with rosbags and every
message is published as the raw CDR bytes it was recorded as (an rclpy publisher of the
topic's message class publishes ``bytes`` as serialized data). Messages go out in bag
order, spaced by their receive times divided by ``--rate``. With ``--clock`` the player
is the time source: it publishes ``/clock`` (rosgraph_msgs/Clock) from the bag time at
the playback position (and does not replay a recorded /clock). ``--loop`` starts again
at the end: the clock jumps back, and the observer node resets on that jump.

QoS: the QoS recorded in the bag's metadata when there is one; otherwise sensor topics
(sensor_msgs types other than the vehicle vectors state/..., control/..., observer/...)
use the sensor-data profile (best effort) and the rest are reliable, depth 10.

"""

import argparse
import importlib
import signal
import sys
import time
import warnings

from .errors import BagToolError
from .reader import BagReader
from ..core.errors import ObserverError, quiet_on_closed_pipe
from ..ros_names import check_domain_id, check_topic_name

__all__ = ['main', 'message_class', 'parse_remap', 'PlayOptions', 'Player']

_VECTOR_SUFFIXES = ('/state/true', '/state/estimate', '/control/u', '/control/reference',
                    '/observer/residual', '/control/u_array')
_NS_PER_S = 1_000_000_000


def message_class(msgtype):
    """
    Return the rclpy message class of a type name (``sensor_msgs/msg/Imu``).

    Imports ``<package>.msg`` (the same on a Jazzy install and from the PyPI wheels).
    Raises BagToolError when the class cannot be imported.

    """
    try:
        pkg, kind, name = msgtype.split('/')
        module = importlib.import_module(f'{pkg}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError, ValueError) as err:
        raise BagToolError(f'no Python message class for {msgtype} ({err})') from None


def parse_remap(text):
    """Parse ``OLD:=NEW`` into absolute topic names."""
    old, sep, new = text.partition(':=')
    if not sep or not old.strip() or not new.strip():
        raise BagToolError(f'--remap {text!r}: expected OLD:=NEW')
    try:
        check_topic_name(new.strip(), '--remap')
    except ObserverError as err:
        raise BagToolError(str(err)) from None
    return _absolute(old.strip()), _absolute(new.strip())


def _absolute(topic):
    return topic if topic.startswith('/') else '/' + topic


class PlayOptions:
    """Playback options (what the command line gives)."""

    def __init__(self, rate=1.0, start=0.0, topics=None, loop=False, clock_hz=None,
                 remap=None, wait_subscribers=0, wait_timeout=30.0, wait_settle=0.5):
        if not rate > 0.0:
            raise BagToolError(f'--rate must be positive; got {rate}')
        if not start >= 0.0:
            raise BagToolError(f'--start must be >= 0; got {start}')
        if clock_hz is not None and not clock_hz > 0.0:
            raise BagToolError(f'--clock must be a positive rate in Hz; got {clock_hz}')
        self.rate = float(rate)
        self.start = float(start)
        self.topics = None if not topics else [_absolute(t) for t in topics]
        self.loop = bool(loop)
        self.clock_hz = clock_hz
        self.remap = dict(remap or {})
        self.wait_subscribers = int(wait_subscribers)
        self.wait_timeout = float(wait_timeout)
        self.wait_settle = float(wait_settle)


def _qos(conn, topic):
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                           qos_profile_sensor_data)
    from rosbags.interfaces import QosDurability, QosReliability
    profiles = getattr(conn.ext, 'offered_qos_profiles', None) or []
    if profiles:
        q = profiles[0]
        best_effort = q.reliability == QosReliability.BEST_EFFORT
        latched = q.durability == QosDurability.TRANSIENT_LOCAL
        return QoSProfile(
            depth=max(int(q.depth or 0), 1 if latched else 10),
            history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else
            ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else
            DurabilityPolicy.VOLATILE)
    if conn.msgtype.startswith('sensor_msgs/msg/') and not topic.endswith(_VECTOR_SUFFIXES):
        return qos_profile_sensor_data
    return QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)


class Player:
    """
    Publish a bag's messages with their recorded timing (scaled by the rate).

    Parameters
    ----------
    node : rclpy.node.Node
        The node that owns the publishers.
    bag : BagReader
        An open bag.
    options : PlayOptions
    log : callable
        ``log(text)`` for notes (default: stderr).

    """

    def __init__(self, node, bag, options, log=None):
        self.node = node
        self.bag = bag
        self.options = options
        self.log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self.publishers = {}          # bag topic -> publisher
        self.played = 0
        self.stop = False
        info = bag.info
        wanted = options.topics
        if wanted is not None:
            missing = [t for t in wanted if t not in info.topics]
            if missing:
                raise BagToolError(f'{info.path}: topics not in the bag: {missing}; topics in '
                                   f'the bag: {info.describe_topics()}')
        for conn in bag.connections():
            topic = conn.topic
            if wanted is not None and topic not in wanted:
                continue
            if options.clock_hz is not None and topic == '/clock':
                self.log("note: the bag's /clock is not played (--clock publishes it)")
                continue
            if topic in self.publishers:
                continue
            try:
                cls = message_class(conn.msgtype)
            except BagToolError as err:
                self.log(f'warning: {topic} skipped: {err}')
                continue
            name = options.remap.get(topic, topic)
            try:
                check_topic_name(name)
            except ObserverError as err:    # a bag from elsewhere: a name rcl refuses
                self.log(f'warning: {topic} skipped: {err} (give it a name with --remap)')
                continue
            self.publishers[topic] = node.create_publisher(cls, name, _qos(conn, topic))
        if not self.publishers and options.clock_hz is None:
            raise BagToolError(f'{info.path}: nothing to play')
        self.clock_pub = None
        if options.clock_hz is not None:
            from rclpy.qos import QoSProfile
            from rosgraph_msgs.msg import Clock
            self._Clock = Clock
            self.clock_pub = node.create_publisher(Clock, '/clock', QoSProfile(depth=10))

    def wait_for_subscribers(self):
        """
        Wait until the publishers have matched ``wait_subscribers`` subscriptions.

        Then wait ``wait_settle`` seconds more: the publisher side of a match comes
        first, and a volatile subscription that has not yet matched the publisher on its
        side would drop the first messages.

        """
        need = self.options.wait_subscribers
        if need <= 0:
            return True
        pubs = list(self.publishers.values()) + ([self.clock_pub] if self.clock_pub else [])
        deadline = time.monotonic() + self.options.wait_timeout
        while not self.stop:
            if sum(p.get_subscription_count() for p in pubs) >= need:
                time.sleep(self.options.wait_settle)
                return True
            if time.monotonic() > deadline:
                self.log(f'warning: fewer than {need} subscriptions after '
                         f'{self.options.wait_timeout:.0f} s; playing anyway')
                return False
            time.sleep(0.01)
        return False

    def _publish_clock(self, bag_ns):
        from builtin_interfaces.msg import Time
        self.clock_pub.publish(self._Clock(clock=Time(sec=int(bag_ns // _NS_PER_S),
                                                      nanosec=int(bag_ns % _NS_PER_S))))

    def flush(self, timeout=2.0):
        """Wait until reliable subscribers acknowledged what was published (at most timeout)."""
        import rclpy
        from rclpy.duration import Duration
        if not rclpy.ok():
            return
        deadline = time.monotonic() + timeout
        for pub in self.publishers.values():
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                return
            try:
                pub.wait_for_all_acked(Duration(seconds=remaining))
            except Exception:   # noqa: BLE001 - best effort publishers, a shut-down context
                pass

    def play(self):
        """Play once (or until stopped / forever with loop); return messages published."""
        import rclpy
        info = self.bag.info
        opts = self.options
        begin = info.start_ns + int(round(opts.start * 1e9))
        topics = list(self.publishers)
        period = None if opts.clock_hz is None else 1.0 / opts.clock_hz
        while not self.stop and rclpy.ok():
            wall0 = time.monotonic()
            next_clock = wall0
            if period is not None:
                self._publish_clock(begin)
                next_clock += period
            for conn, log_ns, raw in self.bag.messages(topics, start=begin):
                target = wall0 + (log_ns - begin) * 1e-9 / opts.rate
                while not self.stop:
                    now = time.monotonic()
                    if period is not None and next_clock <= min(now, target):
                        self._publish_clock(begin + int((next_clock - wall0) * opts.rate * 1e9))
                        next_clock += period
                        continue
                    if now >= target:
                        break
                    wake = target if period is None else min(target, next_clock)
                    time.sleep(max(0.0, min(wake - now, 0.05)))
                if self.stop or not rclpy.ok():
                    break
                pub = self.publishers.get(conn.topic)
                if pub is not None:
                    if period is not None and next_clock <= time.monotonic():
                        # behind: the clock at the message's time stands for the tick
                        # that is due (one clock per period, not one per message)
                        self._publish_clock(log_ns)
                        next_clock += period
                    pub.publish(bytes(raw))
                    self.played += 1
            if not opts.loop:
                break
        return self.played


def _parser():
    parser = argparse.ArgumentParser(
        prog='observer-play',
        description="Publish a bag's recorded messages with their recorded timing, like "
                    '`ros2 bag play` (raw serialized data; rosbags, no ros2bag needed).',
        epilog='exit status: 0 done or interrupted (Ctrl-C); 2 the bag or the arguments '
               'cannot be used (one line "error: ..." on stderr). ROS arguments '
               '(--ros-args ...) are passed to rclpy.')
    parser.add_argument('bag', help='bag directory, or one .mcap or .db3 file')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='playback speed factor (default 1.0; 2.0 = twice as fast)')
    parser.add_argument('--start', type=float, default=0.0, metavar='OFFSET',
                        help='start this many seconds after the beginning of the bag')
    parser.add_argument('--topics', nargs='+', metavar='T', help='play only these topics')
    parser.add_argument('--loop', action='store_true',
                        help='start again at the end (the clock jumps back)')
    parser.add_argument('--clock', nargs='?', type=float, const=40.0, default=None,
                        metavar='HZ', help='publish /clock from the bag time at HZ '
                        '(default 40 Hz when given without a value)')
    parser.add_argument('--remap', action='append', default=[], metavar='OLD:=NEW',
                        help='publish topic OLD as NEW (repeatable)')
    parser.add_argument('--wait-subscribers', type=int, default=0, metavar='N',
                        help='before playing, wait until the publishers have N matched '
                             'subscriptions in total (up to --wait-timeout seconds)')
    parser.add_argument('--wait-timeout', type=float, default=30.0, metavar='S',
                        help='give up waiting for subscriptions after S seconds (default 30)')
    parser.add_argument('--wait-settle', type=float, default=0.5, metavar='S',
                        help='once they are matched, wait S seconds more for the '
                             "subscriptions' side of discovery (default 0.5)")
    return parser


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-play``; returns the exit status."""
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    full = list(sys.argv[1:] if argv is None else argv)
    # ROS arguments come last (--ros-args ...); ours stay away from rcl, which would take
    # our OLD:=NEW remaps for (deprecated) ROS remapping rules
    split = full.index('--ros-args') if '--ros-args' in full else len(full)
    ros_args = full[split:]
    args = _parser().parse_args(full[:split])
    try:
        remap = dict(parse_remap(r) for r in args.remap)
        options = PlayOptions(args.rate, args.start, args.topics, args.loop, args.clock,
                              remap, args.wait_subscribers, args.wait_timeout,
                              args.wait_settle)
        bag = BagReader(args.bag).load()
        check_domain_id()
    except ObserverError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    import rclpy
    from rclpy.executors import ExternalShutdownException
    rclpy.init(args=['observer-play'] + ros_args)
    node = None
    player = None
    code = 0
    try:
        node = rclpy.create_node('observer_play')
        player = Player(node, bag, options)

        def on_signal(signum, frame):
            player.stop = True
        signal.signal(signal.SIGTERM, on_signal)
        info = bag.info
        print(f'playing {info.path} ({info.message_count} messages, '
              f'{(info.end_ns - info.start_ns) * 1e-9:.1f} s) at rate {options.rate:g}'
              f'{", looping" if options.loop else ""}'
              f'{f", /clock at {options.clock_hz:g} Hz" if options.clock_hz else ""}',
              file=sys.stderr, flush=True)
        player.wait_for_subscribers()
        player.play()
    except BagToolError as err:
        print(f'error: {err}', file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:   # noqa: BLE001 - a publish after Ctrl-C shut the context down
        if rclpy.ok():
            raise
        del err
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)     # a second Ctrl-C: clean up anyway
        if player is not None:
            player.flush()
            print(f'published {player.played} messages', file=sys.stderr, flush=True)
        bag.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    raise SystemExit(main())
