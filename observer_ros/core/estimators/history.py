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
them in turn (the same to round-off). A late command is the other exception, below.

A command stamped ahead of the estimate (the compensator's delay compensation stamps its
commands a few steps ahead) is held *pending*: it is applied when the estimate passes its
stamp (a measurement after it; a prediction to or past it uses it), not propagated to at
once. So the measurements that come before its stamp are in order, not late (no rewind),
and the result is that of the stamp order all the same.

A measurement newer than everything held costs little more than the estimator's own step
(benchmarks/README.md): its entry is a plain list placed without a sort key,
and the old entries are dropped when the oldest checkpoint (kept in a deque) leaves the
window, not searched for per message. How a late message is inserted (a rewind from a
checkpoint; for a late command of most estimators, superposition) is :mod:`.rewind`'s.

The node and the bag replay both use this class: what one estimates from a recording,
the other estimates live.

"""

from bisect import bisect_left
from collections import deque
import math
from operator import itemgetter

from .base import TimeOrderError
from .entries import (COMMAND, ESTIMATE, INNOVATION_COV, KIND, MEASUREMENT, new_entry, RESIDUAL,
                      ROWS, STAMP, STATE, TAG, VALUE)
from .rewind import CHECKPOINT_EVERY, DENSE_DEPTH, DENSE_FOR, Rewinding
from ..spec import HISTORY_LENGTH

__all__ = ['History', 'HISTORY_LENGTH', 'HISTORY_MAX_MESSAGES', 'CHECKPOINT_EVERY',
           'DENSE_DEPTH', 'DENSE_FOR']

#: At most this many messages are kept, whatever their stamps (a bound on the memory and
#: on the cost of a rewind when stamps crowd: 2.5e4 is 0.25 s at 100 kHz). When it is
#: reached, the oldest are dropped and the window is shorter.
HISTORY_MAX_MESSAGES = 25000

_stamp = itemgetter(STAMP)


class History(Rewinding):
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
    the bag replay overwrites what it had recorded for them. It is a new list after a
    call that revised some; otherwise the same empty list.

    """

    def __init__(self, estimator, length=HISTORY_LENGTH, max_messages=HISTORY_MAX_MESSAGES):
        length = float(length)
        if not (length >= 0.0 and math.isfinite(length)):
            raise ValueError(f'history length must be >= 0 and finite; got {length!r}')
        if int(max_messages) < 1:
            raise ValueError(f'max_messages must be at least 1; got {max_messages!r}')
        self._est = estimator
        self._length = length
        self._max = int(max_messages)
        self.revised = []
        self.rewinds = 0
        self.reapplied = 0
        self.superposed = 0
        #: Insert a late command by superposition where the estimator allows it (see
        #: :meth:`_superpose`); False: re-apply the messages after it (to the last bit).
        self.superpose = True
        self._clear()

    def _clear(self):
        self._entries = []                        # applied, in stamp order
        self._pending = []                        # commands not before the estimate's t
        self._since = 0                           # messages since the last checkpoint
        self._base = self._est.save_state()      # the state before the first entry
        self._dropped_t = -math.inf               # the newest stamp no longer kept
        self._checkpoints = deque()               # the entries with a state, in order
        self._dense = 0                           # messages still checkpointed each
        self._residual = None
        self._S = None
        self._x_at = None

    # ------------------------------------------------------------ properties

    @property
    def estimator(self):
        """Return the estimator this history drives (it is at the newest stamp applied)."""
        return self._est

    @property
    def length(self):
        """Seconds of messages kept before the newest stamp."""
        return self._length

    @property
    def t(self):
        """Time of the estimate, or None before the first message (pending commands aside)."""
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
        """Return the tag of the newest message applied (None when there is none)."""
        return self._entries[-1][TAG] if self._entries else None

    @property
    def pending(self):
        """Return the number of commands held until the estimate reaches their stamps."""
        return len(self._pending)

    def __len__(self):
        return len(self._entries) + len(self._pending)

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
            The estimate at the newest stamp applied (t itself unless the measurement is
            late). Not to be modified: it may be :attr:`x_at_stamp` itself.

        Raises
        ------
        TimeOrderError
            t is older than the history.
        ObserverError
            A bad measurement (the history is left as it was).

        """
        est = self._est
        if rows is None:
            rows = est.measured_rows
        elif type(rows) is not tuple:
            rows = tuple(rows)
        if self.revised:
            self.revised = []
        entries = self._entries
        pending = self._pending
        if entries and type(t) is float and (not pending or pending[0][STAMP] >= t):
            last = entries[-1]
            if last[STAMP] < t or (last[STAMP] == t and last[KIND] == MEASUREMENT):
                # in order, nothing pending before it: the estimator is at the last entry
                # and this is its step, an entry and a checkpoint every CHECKPOINT_EVERY
                x = est.correct(t, y, rows)         # refuses a non-finite t
                residual, S = est.last_residual()
                since = self._since + 1
                state = None
                if since >= CHECKPOINT_EVERY or self._dense:
                    since, state = 0, est.save_state()
                    if self._dense:
                        self._dense -= 1
                self._since = since
                # x, residual and S are not kept: a rewind computes them again, and they
                # go when the caller is done with them (memory reused, not held)
                entry = [t, MEASUREMENT, y, rows, tag, state, None, None, None]
                entries.append(entry)
                checkpoints = self._checkpoints
                if state is not None:
                    checkpoints.append(entry)
                self._drop_if_due(t)
                self._residual, self._S, self._x_at = residual, S, x
                return x
        entry = self._insert(MEASUREMENT, est._as_time(t), y, rows, tag)
        self._residual = entry[RESIDUAL]
        self._S = entry[INNOVATION_COV]
        self._x_at = entry[ESTIMATE]
        return est.x_hat

    def set_input(self, t, u, tag=None):
        """
        Hold the input u from its stamp t on (from the newest stamp if older than the history).

        A stamp after the estimate's time is held pending: applied when the estimate
        passes it (:meth:`correct` after it; :meth:`predict` to or past it uses it without
        applying it). Measurements at its stamp come before it, as in the stamp order.

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
        est = self._est
        t = est._as_time(t)
        if self.revised:
            self.revised = []
        head = est.t
        pending = self._pending
        entries = self._entries
        if t == head and not pending and entries and entries[-1][STAMP] == t:
            # the closed loop's command in order (it answers the newest measurement): the
            # estimator is at the last entry and this is the next, as _insert would find
            entry = new_entry(t, COMMAND, u, (), tag)
            self._apply(entry)                  # a bad input raises, changing nothing
            entries.append(entry)
            self._drop_if_due(t)
            return False
        if head is not None and (t > head or (pending and pending[0][STAMP] <= t)):
            # ahead of the estimate (or after commands held at its stamp): held
            self._hold(new_entry(t, COMMAND, est.check_input(u), (), tag))
            return False
        late = not self.accepts(t)
        if late:
            t = head
        self._insert(COMMAND, t, u, (), tag)
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
            The prediction at t with the input held, pending commands stamped up to t
            included.

        """
        est = self._est
        state = est.save_state()
        try:
            for e in self._pending:
                if e[STAMP] > t:
                    break
                est.set_input(e[STAMP], e[VALUE])
            return est.predict(t)
        finally:
            est.restore_state(state)

    def forget(self):
        """
        Start the history again from the estimator's present state.

        For a caller that drove the estimator directly (the bag replay's bulk stretches):
        no message stamped at or before the estimate's time is accepted after this; the
        pending commands stamped after it stay pending.

        """
        head = self._est.t
        pending = [e for e in self._pending if head is None or e[STAMP] > head]
        self._clear()
        self._pending = pending
        if head is not None:
            self._dropped_t = head

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
        """Insert a message at its place among the entries applied (a rewind if late)."""
        est = self._est
        if not self.accepts(t):
            raise TimeOrderError(f'time {t!r} s is older than the history '
                                 f'({self._length:g} s before {est.t!r} s)')
        entry = new_entry(t, kind, value, rows, tag)
        entries = self._entries
        pos = len(entries)
        while pos and (entries[pos - 1][STAMP] > t or
                       (entries[pos - 1][STAMP] == t and entries[pos - 1][KIND] > kind)):
            pos -= 1
        if pos == len(entries):
            self._append(entry)          # in order: the estimator is at the last entry
        else:
            self._rewind(pos, entry)
        self._drop_old()
        return entry

    def _append(self, entry):
        """Apply an entry newer than those applied, the pending commands before it first."""
        pending = self._pending
        t = entry[STAMP]
        if pending and pending[0][STAMP] < t:
            if entry[KIND] == MEASUREMENT:            # a bad one changes nothing
                self._est.check_measurement(entry[VALUE], entry[ROWS])
            self._apply_pending(t)
        self._apply(entry)
        self._entries.append(entry)

    def _hold(self, entry):
        """Keep a command stamped after the estimate until the estimate reaches it."""
        pending = self._pending
        t = entry[STAMP]
        pos = len(pending)
        while pos and pending[pos - 1][STAMP] > t:      # arrival order at one stamp
            pos -= 1
        pending.insert(pos, entry)
        if len(self) > self._max:            # bounded: the oldest reaches the estimate
            self._apply_pending(pending[0][STAMP], True)
            self._drop_old()

    def _apply_pending(self, t, inclusive=False):
        """Apply the pending commands stamped before t (or at t too, if inclusive)."""
        pending = self._pending
        n = 0
        for e in pending:
            if e[STAMP] > t or (e[STAMP] == t and not inclusive):
                break
            self._apply(e)
            self._entries.append(e)
            n += 1
        del pending[:n]

    def _drop_if_due(self, t):
        """After an entry at t appended in order: drop the old ones if the window or count asks."""
        checkpoints = self._checkpoints
        if (checkpoints and checkpoints[0][STAMP] < t - self._length) or \
                len(self._entries) > self._max:
            self._drop_old()

    def _drop_old(self):
        """
        Drop the entries up to the newest checkpoint older than the window.

        The state of the last entry dropped becomes the base of a rewind, so the entries
        go a checkpoint's worth at a time: fewer for the window, more for the number of
        messages (max_messages). The newest entry is kept whatever its stamp.
        """
        entries = self._entries
        if not entries:
            return
        horizon = self._est.t - self._length
        checkpoints = self._checkpoints
        newest = entries[-1]
        upto = None
        while checkpoints and checkpoints[0][STAMP] < horizon and checkpoints[0] is not newest:
            upto = checkpoints.popleft()
        drop = 0 if upto is None else _position(entries, upto) + 1
        if len(entries) - drop > self._max:         # rare: stamps crowd
            last = len(entries) - 1
            drop = len(entries) - self._max
            while drop < last and entries[drop - 1][STATE] is None:
                drop += 1
            if entries[drop - 1][STATE] is None:
                drop = 0
            upto = True                             # the checkpoints listed again below
        if drop > 0:
            self._base = entries[drop - 1][STATE]
            self._dropped_t = max(self._dropped_t, entries[drop - 1][STAMP])
            del entries[:drop]
            if upto is True:
                self._find_checkpoints()


def _position(entries, entry):
    """
    Return the index of ``entry`` itself (by identity) in the stamp-ordered ``entries``.

    Never by equality: two messages with one stamp and equal values (a stream arriving
    twice) are equal lists up to their saved states, numpy arrays, which cannot be
    compared as one truth value. A bisection on the stamps, then identity among the
    entries of that stamp.
    """
    i = bisect_left(entries, entry[STAMP], key=_stamp)
    while entries[i] is not entry:
        i += 1
    return i
