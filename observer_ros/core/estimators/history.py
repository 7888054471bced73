# observer_ros.core.estimators.history: late and out-of-order messages, by rewinding.
"""
A bounded history of an estimator's messages, replayed from the stamp of a late one.

Sensors have different latencies: a gyro arrives 1 ms after its stamp, a vision fix
tens of milliseconds later, so a message is often older than the estimate. The
:class:`History` keeps the estimator's state after each measurement and command of
the last ``length`` seconds (before the newest stamp). A message stamped inside that
window is inserted at its own stamp: the state just before it is restored, the message
applied, and every later message applied again, once (one rewind per message, whatever
its place). A message older than the window is refused (:meth:`History.accepts`), as
robot_localization's ``history_length`` does.

The order of the messages in the history is that of their stamps; at one stamp the
measurements come before the commands (the lock-step protocol: the command answering a
measurement carries its stamp), and messages of one kind in the order they arrived (so
messages that arrive in stamp order never cause a rewind, and the bag replay of a
recording gives what the node computed). So the same messages give the same estimate in
any arrival order whose lateness stays inside the window: the calls made on the
estimator are those of the stamp order, on the states it had then
(:meth:`Estimator.save_state`), hence the same to the last bit. Only measurements of
several sensors at one stamp may then come in another order: the full- and reduced-order
observers fuse them into one correction (the same result), a Kalman filter updates with
them in turn (the same to round-off).

The node and the bag replay both use this class: what one estimates from a recording,
the other estimates live.

"""

import bisect

import numpy as np

from .base import TimeOrderError
from ..spec import HISTORY_LENGTH

__all__ = ['History', 'HISTORY_LENGTH', 'HISTORY_MAX_MESSAGES', 'CHECKPOINT_EVERY']

#: At most this many messages are kept, whatever their stamps (a bound on the memory and
#: on the cost of a rewind when stamps crowd: 2.5e4 is 0.25 s at 100 kHz). When it is
#: reached, the oldest are dropped and the window is shorter.
HISTORY_MAX_MESSAGES = 25000

#: The estimator's state is kept after every this many messages (a checkpoint); a rewind
#: starts from the newest checkpoint before the late message and re-applies the messages
#: in between (at most this many more). Copying the state after every message cost
#: about as much as the correction itself (benchmarks/README.md, P5).
CHECKPOINT_EVERY = 8

_MEASUREMENT, _COMMAND = 0, 1


class _Entry:
    """One message of the history, and the estimator's state after it."""

    __slots__ = ('key', 'kind', 't', 'value', 'rows', 'tag', 'state', 'x', 'residual', 'S')

    def __init__(self, key, kind, t, value, rows, tag):
        self.key = key
        self.kind = kind
        self.t = t
        self.value = value
        self.rows = rows
        self.tag = tag
        self.state = None
        self.x = None
        self.residual = None
        self.S = None


class History:
    """
    An estimator with a bounded history of its messages, for late ones.

    Parameters
    ----------
    estimator : Estimator
        The estimator (from :func:`make_estimator`); this object calls it from now on.
    length : float
        Seconds of messages kept before the newest stamp, >= 0 (0: a message older than
        the estimate is refused, as without a history).
    max_messages : int
        At most this many messages kept (see :data:`HISTORY_MAX_MESSAGES`).

    Notes
    -----
    :attr:`revised` lists, after each call, the measurements whose estimate changed
    because a late message was inserted before them, as ``(tag, x_hat, residual, S)``:
    the bag replay overwrites what it had recorded for them.

    """

    def __init__(self, estimator, length=HISTORY_LENGTH, max_messages=HISTORY_MAX_MESSAGES):
        length = float(length)
        if not (length >= 0.0 and np.isfinite(length)):
            raise ValueError(f'history length must be >= 0 and finite; got {length!r}')
        if int(max_messages) < 1:
            raise ValueError(f'max_messages must be at least 1; got {max_messages!r}')
        self._est = estimator
        self._length = length
        self._max = int(max_messages)
        self._seq = 0
        self.revised = []
        self.rewinds = 0
        self.reapplied = 0
        self._clear()

    def _clear(self):
        self._entries = []
        self._keys = []
        self._since = 0                           # messages since the last checkpoint
        self._base = self._est.save_state()      # the state before the first entry
        self._dropped_t = -np.inf                 # the newest stamp no longer kept
        self._residual = None
        self._S = None
        self._x_at = None

    # ------------------------------------------------------------ properties

    @property
    def estimator(self):
        """Return the estimator this history drives (it is at the newest stamp)."""
        return self._est

    @property
    def length(self):
        """Seconds of messages kept before the newest stamp."""
        return self._length

    @property
    def t(self):
        """Time of the estimate (the newest stamp), or None before the first message."""
        return self._est.t

    @property
    def x_hat(self):
        """Return the estimate at :attr:`t` (a copy)."""
        return self._est.x_hat

    @property
    def residual(self):
        """Residual of the measurement of the last :meth:`correct` call, or None."""
        return self._residual

    @property
    def innovation_covariance(self):
        """Covariance S of :attr:`residual` (Kalman), or None."""
        return self._S

    @property
    def x_at_stamp(self):
        """Return the estimate at the stamp of the last :meth:`correct` call, after it."""
        return self._x_at

    @property
    def head_tag(self):
        """Return the tag of the newest message of the history (None when empty)."""
        return self._entries[-1].tag if self._entries else None

    def __len__(self):
        return len(self._entries)

    # ------------------------------------------------------------ calls

    def accepts(self, t):
        """
        Tell whether a message stamped t can be used (inside the history or newer).

        Parameters
        ----------
        t : float
            Stamp in seconds.

        Returns
        -------
        ok : bool
            False when t is more than :attr:`length` before the estimate's time, or not
            after a message already dropped from the history.

        """
        head = self._est.t
        return head is None or t >= head or (t >= head - self._length and t > self._dropped_t)

    def correct(self, t, y, rows=None, tag=None):
        """
        Use a measurement stamped t: at its place in the history if it is late.

        Parameters
        ----------
        t : float
            Stamp in seconds (:meth:`accepts` must hold).
        y : array_like
            Measured values of the outputs ``rows``.
        rows : sequence of int, optional
            Output rows; default all measured rows.
        tag : object, optional
            Kept with the message (given back in :attr:`revised` and :attr:`head_tag`).

        Returns
        -------
        x_hat : ndarray
            The estimate at the newest stamp (t itself unless the measurement is late).

        Raises
        ------
        TimeOrderError
            t is older than the history.
        ObserverError
            A bad measurement (the history is left as it was).

        """
        rows = self._est.measured_rows if rows is None else tuple(rows)
        entry = self._insert(_MEASUREMENT, t, y, rows, tag)
        self._residual = entry.residual
        self._S = entry.S
        self._x_at = entry.x
        return self._est.x_hat

    def set_input(self, t, u, tag=None):
        """
        Hold the input u from its stamp t on (from the newest stamp if older than the history).

        Parameters
        ----------
        t : float
            Stamp in seconds.
        u : array_like
            The input (m).
        tag : object, optional
            Kept with the message.

        Returns
        -------
        late : bool
            True when the stamp was older than the history and u is held from the
            estimate's time instead (as an estimator without a history does).

        """
        late = not self.accepts(t)
        if late:
            t = self._est.t
        self._insert(_COMMAND, t, u, (), tag)
        return late

    def predict(self, t):
        """
        Return the estimate predicted to t, leaving the history as it is.

        Parameters
        ----------
        t : float
            Time in seconds, not before :attr:`t`.

        Returns
        -------
        x_hat : ndarray
            The prediction at t with the held input.

        """
        est = self._est
        state = est.save_state()
        try:
            return est.predict(t)
        finally:
            est.restore_state(state)

    def forget(self):
        """
        Start the history again from the estimator's present state.

        For a caller that drove the estimator directly (the bag replay's bulk stretches):
        no message stamped at or before the estimate's time is accepted after this.

        """
        self._clear()
        if self._est.t is not None:
            self._dropped_t = self._est.t

    def reset(self, x0=None, t0=None):
        """
        Reset the estimator (see :meth:`Estimator.reset`) and forget the history.

        Parameters
        ----------
        x0 : array_like, optional
            New initial estimate; default the estimator's own.
        t0 : float, optional
            Its time; default None (the time of the next message).

        """
        self._est.reset(x0, t0)
        self._clear()
        self.revised = []

    # ------------------------------------------------------------ internals

    def _insert(self, kind, t, value, rows, tag):
        est = self._est
        t = est._as_time(t)
        if not self.accepts(t):
            raise TimeOrderError(f'time {t!r} s is older than the history '
                                 f'({self._length:g} s before {est.t!r} s)')
        self._seq += 1
        key = (t, kind, self._seq)
        entry = _Entry(key, kind, t, value, rows, tag)
        keys = self._keys
        self.revised = []
        if not keys or key > keys[-1]:
            self._apply(entry)               # in order: the estimator is at the last entry
            keys.append(key)
            self._entries.append(entry)
        else:
            self._rewind(bisect.bisect_right(keys, key), entry)
        self._drop_old()
        return entry

    def _apply(self, entry, checkpoint=None):
        """Apply an entry; keep the state after it every CHECKPOINT_EVERY messages."""
        est = self._est
        if entry.kind == _MEASUREMENT:
            entry.x = est.correct(entry.t, entry.value, entry.rows)
            entry.residual = est.residual
            entry.S = est.innovation_covariance
        else:
            est.set_input(entry.t, entry.value)
        if checkpoint is None:
            self._since += 1
            checkpoint = self._since >= CHECKPOINT_EVERY
            if checkpoint:
                self._since = 0
        entry.state = est.save_state() if checkpoint else None

    def _rewind(self, pos, entry):
        est = self._est
        entries = self._entries
        # the newest checkpoint before the new entry, and the entries from it on
        start = pos
        while start > 0 and entries[start - 1].state is None:
            start -= 1
        head = est.save_state()
        est.restore_state(entries[start - 1].state if start else self._base)
        # checkpoints again every CHECKPOINT_EVERY messages from the one restored
        count = 0
        try:
            for e in entries[start:pos]:                  # unchanged: before the new one
                count += 1
                self._apply(e, count % CHECKPOINT_EVERY == 0)
            count += 1
            self._apply(entry, count % CHECKPOINT_EVERY == 0)
        except Exception:
            # a bad message changes nothing (the states the entries before it got are
            # those they had: the same messages from the same checkpoint)
            est.restore_state(head)
            raise
        self.rewinds += 1
        later = entries[pos:]
        for e in later:
            count += 1
            self._apply(e, count % CHECKPOINT_EVERY == 0)
            if e.kind == _MEASUREMENT:
                self.revised.append((e.tag, e.x, e.residual, e.S))
        self._since = count % CHECKPOINT_EVERY
        self.reapplied += len(later) + pos - start
        entries.insert(pos, entry)
        self._keys.insert(pos, entry.key)

    def _drop_old(self):
        entries = self._entries
        horizon = self._est.t - self._length
        last = len(entries) - 1       # the newest entry is kept whatever its stamp
        # the state after the last dropped entry becomes the base, so drop up to the
        # newest checkpoint older than the horizon: fewer for the horizon, more for the
        # number of messages (below)
        drop = j = 0
        while j < last and entries[j].t < horizon:     # at most CHECKPOINT_EVERY or so
            if entries[j].state is not None:
                drop = j + 1
            j += 1
        if len(entries) - drop > self._max:
            drop = len(entries) - self._max
            while drop < last and entries[drop - 1].state is None:
                drop += 1
            if entries[drop - 1].state is None:
                drop = 0
        if drop > 0:
            self._base = entries[drop - 1].state
            self._dropped_t = max(self._dropped_t, entries[drop - 1].t)
            del entries[:drop]
            del self._keys[:drop]
