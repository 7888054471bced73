# observer_ros.nodes.callback_watch: a node's callbacks watched from a thread of its own.
"""
How far behind its input a node is, messages shed in a flood, /diagnostics on time.

rclpy's EventsExecutor (the nodes' executor, :func:`~observer_ros.nodes.runner.make_executor`)
queues one event per message received, in a queue without a bound, and runs timers from the
same queue. A flood faster than the callbacks (16 kHz of Imu on the observer's sensor topic)
therefore grew the process by 2 MB/s, and /diagnostics, a timer, came 5 to 8 s late. The
reader's depth (``SENSOR_SUB_QOS``, 100) bounds only what DDS holds, not the queue.

:class:`CallbackWatch` measures the queue's delay with a heartbeat timer (every
:data:`BEAT` s, queued like any callback) read from a thread of its own:

- **a flood**: when the heartbeat is more than :data:`LAG_LIMIT` s late while the guarded
  subscriptions still take messages (at least :data:`FLOOD_MESSAGES` since the last beat:
  the executor is working through a backlog, not stuck in one long callback), their
  messages are dropped (taken without being deserialised: the subscriptions read raw
  bytes, as the observer's and the compensator's always do) until the heartbeat is back
  within :data:`LAG_RESUME` s. The queue then holds at
  most about LAG_LIMIT s of events, and the node reports ERROR ``flooded`` naming the topic
  and its rate, with the ``flood_dropped`` count. Taking a message raw and dropping it
  costs about 14 us of the executor's thread (40 us deserialised): about 70 000 messages/s
  on one core;
- **the events executor left at the first flood**: its queue grows with the flood even
  while messages are shed (over a 60 s flood of 18 to 30 kHz the process grew 6 to 14 MB,
  and more the faster the flood), so ``overrun`` is set when shedding starts, and
  :func:`~observer_ros.nodes.runner.run_nodes` drops that queue at once (shutting the
  executor down) and goes on in rclpy's wait-set executor, whose memory is bounded by the
  readers' depth, for the rest of the run;
- **/diagnostics on time**: when the node's own report is overdue (1.5 periods), the
  thread publishes one for it (ERROR, how many seconds the callbacks are behind, the
  counters as last seen), every period until the node's own timer reports again.

No message is dropped while the executor keeps up (a healthy observer at 1 kHz, a slow
design at the first step: one long callback takes no messages, nothing is shed).

"""

import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus

__all__ = ['BEAT', 'LAG_LIMIT', 'LAG_RESUME', 'FLOOD_MESSAGES', 'FLOOD_HOLD', 'CallbackWatch']

# s (wall): the heartbeat's period, and how often the thread looks (each look is a
# wake-up of the process, which an idle node pays as much as a message: ten a second see
# a LAG_LIMIT late heartbeat within 0.1 s)
BEAT = 0.1
WATCH = 0.1
# s: the heartbeat this late, with messages still being taken: a flood; messages are shed
LAG_LIMIT = 0.5
# s: back within this: no more shedding
LAG_RESUME = 0.2
# messages taken since the last heartbeat that make a late heartbeat a flood
FLOOD_MESSAGES = 100
# s (wall): a flood stays reported (ERROR) this long after the last message shed
FLOOD_HOLD = 2.0


class _Guarded:
    """One guarded subscription: its topic, the messages taken and dropped."""

    __slots__ = ('subscription', 'topic', 'raw', 'taken', 'dropped', 'rate', 'mark')

    def __init__(self, topic, raw):
        self.subscription = None
        self.topic = topic
        self.raw = raw              # the callback takes bytes (always, not only when shed)
        self.taken = self.dropped = self.mark = 0
        self.rate = 0.0


class CallbackWatch:
    """
    Watch a node's executor from a thread: its lag, floods, overdue diagnostics.

    Parameters
    ----------
    node : VehicleNode
        The node: ``wall_timer`` for the heartbeat, ``resolve_topic_name``.
    publish : callable
        ``publish(level, message, values)``: how the thread reports for the node when its
        own report is overdue.
    period : callable
        Returns the node's diagnostics period (s), or None (the thread never reports).

    """

    def __init__(self, node, publish, period):
        self._node = node
        self._publish = publish
        self._period = period
        self._guarded = []
        self._beat_at = None
        self._taken_at_beat = 0
        self.shedding = False
        self.overrun = False
        self.may_overrun = True     # False once the process left the events executor
        self.flood_episodes = 0
        self._flood_at = None
        self._flood_text = ''
        self.lag = 0.0
        self.status_at = None       # the node's own last report (wall)
        self.reported_at = None     # the last report on /diagnostics, either one
        self._stop = threading.Event()
        self._thread = None
        self._timer = node.wall_timer(BEAT, self._beat)

    # -- the executor's side --------------------------------------------------------------
    def guard(self, topic, callback, raw=False):
        """
        Return ``(entry, callback)``: ``callback`` wrapped to be shed in a flood.

        Set ``entry.subscription`` to the subscription made with the wrapped callback;
        ``raw``: it takes its messages as bytes.
        """
        entry = _Guarded(topic, raw)
        self._guarded.append(entry)

        if raw:
            def on_message(msg):
                entry.taken += 1
                if self.shedding:
                    entry.dropped += 1
                    return
                callback(msg)
        else:
            def on_message(msg):
                entry.taken += 1
                # bytes: taken raw while shedding (raw is set back just after shedding)
                if self.shedding or msg.__class__ is bytes:
                    entry.dropped += 1
                    return
                callback(msg)
        return entry, on_message

    def forget(self, subscription):
        """Stop guarding a subscription (destroyed: a managed node deactivated)."""
        self._guarded = [e for e in self._guarded if e.subscription is not subscription]

    def _beat(self):
        self._beat_at = time.monotonic()
        self._taken_at_beat = self._taken()
        if self._thread is None:        # the executor spins: watch from now on
            self._thread = threading.Thread(target=self._run, daemon=True,
                                            name=f'watch {self._node.get_name()}')
            self._thread.start()

    def _taken(self):
        return sum(entry.taken for entry in self._guarded)

    def dropped(self):
        """Return the messages shed so far (all guarded subscriptions)."""
        return sum(entry.dropped for entry in self._guarded)

    def status(self, now=None):
        """Return ``(level, message)`` while a flood is reported, else None."""
        now = time.monotonic() if now is None else now
        if self._flood_at is None or (not self.shedding and now - self._flood_at > FLOOD_HOLD):
            return None
        return DiagnosticStatus.ERROR, self._flood_text

    def values(self):
        """Return the counters for /diagnostics: lag, messages shed (once there were any)."""
        out = {}
        if self.flood_episodes:
            out.update(flood_dropped=self.dropped(), flood_episodes=self.flood_episodes)
        if self.lag >= LAG_RESUME:
            out['callback_lag_s'] = f'{self.lag:.2f}'
        return out

    def stop(self):
        """Stop the thread (the node is being destroyed)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)

    # -- the thread -----------------------------------------------------------------------
    def _run(self):
        rate_at = time.monotonic()
        while not self._stop.wait(WATCH):
            try:
                now = time.monotonic()
                if now - rate_at >= 1.0:
                    for entry in self._guarded:
                        taken = entry.taken
                        entry.rate = (taken - entry.mark) / (now - rate_at)
                        entry.mark = taken
                    rate_at = now
                self._look(now)
            except Exception:   # noqa: BLE001 - the node is gone (shut down): stop watching
                return

    def _look(self, now):
        age = now - self._beat_at
        self.lag = max(0.0, age - BEAT)
        if not self.shedding and age > LAG_LIMIT and \
                self._taken() - self._taken_at_beat >= FLOOD_MESSAGES:
            self._shed(True)
            if self.may_overrun:        # the events executor's queue: dropped at once
                self.overrun = True
        elif self.shedding and age < LAG_RESUME:
            self._shed(False)
        if self.shedding:
            self._flood_at = now
            busiest = max(self._guarded, key=lambda e: e.rate)
            # the rates are sampled each second: a flood that began since, by the messages
            # taken since the last heartbeat
            rate = max(busiest.rate, (self._taken() - self._taken_at_beat) / max(age, BEAT))
            self._flood_text = (
                f'flooded: {self._node.resolve_topic_name(busiest.topic)} at '
                f'{rate:.0f} messages/s; {self.dropped()} messages dropped while the '
                f'callbacks were more than {LAG_LIMIT:g} s behind')
        period = self._period()
        if not period:
            return
        own = self.status_at if self.status_at is not None else self._beat_at
        last = self.reported_at if self.reported_at is not None else own
        if now - own > 1.5 * period and now - last >= period:
            status = self.status(now)
            text = status[1] if status else (
                f'no callback has run for {age:.1f} s (one long computation, or no CPU)')
            values = {'callback_lag_s': f'{self.lag:.2f}'}
            if self.flood_episodes:
                values['flood_dropped'] = self.dropped()
            self._publish(DiagnosticStatus.ERROR, f'late: {text}', values)
            self.reported_at = now

    def _shed(self, on):
        """Start or stop shedding: the guarded subscriptions take raw bytes meanwhile."""
        if on:
            self.flood_episodes += 1
        self.shedding = on
        for entry in self._guarded:
            if entry.subscription is not None and not entry.raw:
                entry.subscription.raw = on
        if on:
            self._node.get_logger().error(
                f'callbacks more than {LAG_LIMIT:g} s behind a flood of messages: dropping '
                'them until they catch up (see /diagnostics)', throttle_duration_sec=5.0)
