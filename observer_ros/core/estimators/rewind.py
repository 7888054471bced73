# observer_ros.core.estimators.rewind: a late message inserted among those applied.
"""
How :class:`~.history.History` inserts a message older than the estimate.

The history keeps its entries in stamp order, with the estimator's state after some of
them (checkpoints, every :data:`CHECKPOINT_EVERY` messages). A late message is placed at
its stamp: the state just before its place is restored from the newest checkpoint before
it, the message applied, and every later entry applied again, once
(:meth:`Rewinding._rewind`).

A message stamped a few entries before the newest (the closed loop's command, a step or
a few late) turns on dense checkpoints (:data:`DENSE_DEPTH`): the next such message
re-applies only the entries after it (benchmarks/README.md).

A late command is not even applied again with the entries after it where the estimator
is linear with gains that do not depend on the input (observers given poles, the Kalman
filter, the model alone): its input change is added to the states kept after it
(:mod:`.superposition`, :meth:`Rewinding._superpose`), the stamp order's result to
round-off rather than to the last bit. The observers given a gain (which hold the
measured outputs between samples), and a command older than the states kept densely, are
rewound. A command just before the newest entry, a measurement (the closed loop's command
a step late, most of them), moves the estimator itself: no state need be kept for it
(:meth:`Rewinding._superpose_head`).

"""

from collections import deque

from .entries import (COMMAND, ESTIMATE, INNOVATION_COV, KIND, MEASUREMENT, RESIDUAL, ROWS, STAMP,
                      STATE, TAG, VALUE)
from .superposition import shifted_states

__all__ = ['Rewinding', 'CHECKPOINT_EVERY', 'DENSE_DEPTH', 'DENSE_FOR']

#: The estimator's state is kept after every this many messages (a checkpoint); a rewind
#: starts from the newest checkpoint before the late message and re-applies the messages
#: in between (at most this many more). Copying the state after every message cost
#: about as much as the correction itself (benchmarks/README.md, P5).
CHECKPOINT_EVERY = 8

#: A message inserted at most this many entries before the newest (in the closed loop,
#: the compensator's command answering an estimate arrives after the next measurement,
#: or a few of them on a loaded host) turns on dense checkpoints: the state after every
#: message is kept for the next :data:`DENSE_FOR` messages. The next such message then
#: restores the state just before its place and re-applies only the entries after it, not
#: those since the last regular checkpoint. Messages in order keep the regular ones.
DENSE_DEPTH = 32

#: Messages that keep the state after them once a shallow rewind (:data:`DENSE_DEPTH`)
#: turned dense checkpoints on.
DENSE_FOR = 64


class Rewinding:
    """
    The insertion of late messages: a part of :class:`~.history.History`.

    It works on the history's entries, checkpoints and estimator. :meth:`_apply` is also
    how the history applies a message in order.

    """

    def _apply(self, entry, checkpoint=None):
        """Apply an entry; keep the state after it every CHECKPOINT_EVERY messages."""
        est = self._est
        if entry[KIND] == MEASUREMENT:
            entry[ESTIMATE] = est.correct(entry[STAMP], entry[VALUE], entry[ROWS])
            entry[RESIDUAL], entry[INNOVATION_COV] = est.last_residual()
        else:
            est.set_input(entry[STAMP], entry[VALUE])
        since_counted = checkpoint is None
        if since_counted:
            since = self._since + 1
            checkpoint = since >= CHECKPOINT_EVERY or self._dense > 0
            self._since = 0 if checkpoint else since
        entry[STATE] = est.save_state() if checkpoint else None
        if checkpoint and since_counted:
            self._checkpoints.append(entry)        # a rewind lists them again at its end

    def _rewind(self, pos, entry):
        est = self._est
        entries = self._entries
        if pos == len(entries) - 1 and entry[KIND] == COMMAND and self.superpose and \
                est._superposable and entries[pos][KIND] == MEASUREMENT:
            self._superpose_head(entry)         # the closed loop's command, a step late
            return
        shallow = len(entries) - pos <= DENSE_DEPTH
        if shallow:                                   # the closed loop's lag
            self._dense = DENSE_FOR
        if entry[KIND] == COMMAND and self.superpose and est._superposable and \
                self._superpose(pos, entry):
            return
        if shallow:
            if pos == len(entries) - 1 and pos and entries[pos - 1][STATE] is not None:
                self._rewind_one(entry, entries[pos - 1][STATE])
                return
        dense = self._dense > 0
        # the newest checkpoint before the new entry, and the entries from it on
        start = pos
        while start > 0 and entries[start - 1][STATE] is None:
            start -= 1
        head = est.save_state()
        est.restore_state(entries[start - 1][STATE] if start else self._base)
        # checkpoints again every CHECKPOINT_EVERY messages from the one restored
        count = 0
        try:
            for e in entries[start:pos]:                  # unchanged: before the new one
                count += 1
                self._apply(e, dense or count % CHECKPOINT_EVERY == 0)
            count += 1
            self._apply(entry, dense or count % CHECKPOINT_EVERY == 0)
        except Exception:
            # a bad message changes nothing (the states the entries before it got are
            # those they had: the same messages from the same checkpoint)
            est.restore_state(head)
            self._find_checkpoints()
            raise
        self.rewinds += 1
        later = entries[pos:]
        revised = []
        for e in later:
            count += 1
            self._apply(e, dense or count % CHECKPOINT_EVERY == 0)
            if e[KIND] == MEASUREMENT:
                revised.append((e[TAG], e[ESTIMATE], e[RESIDUAL], e[INNOVATION_COV]))
        if revised:
            self.revised = revised
        self._since = 0 if dense else count % CHECKPOINT_EVERY
        self.reapplied += len(later) + pos - start
        entries.insert(pos, entry)
        # the checkpoints before the one restored are unchanged; those after it moved
        checkpoints = self._checkpoints
        kept = entries[start - 1] if start else None
        while checkpoints and checkpoints[-1] is not kept:
            checkpoints.pop()
        if kept is not None and not checkpoints:     # not listed: list them all again
            self._find_checkpoints()
        else:
            checkpoints.extend(e for e in entries[start:] if e[STATE] is not None)

    def _superpose(self, pos, entry):
        """
        Insert a late command by adding its input change to the states after it.

        Every entry after the command must have its state (the dense checkpoints of the
        closed loop give them); the states, estimates and residuals after it become
        those of the stamp order, to round-off (:mod:`.superposition`), and no message
        is applied again. Returns False, changing nothing, when it cannot be done (the
        caller rewinds); raises, changing nothing, for a bad input.
        """
        est = self._est
        entries = self._entries
        later = entries[pos:]
        for e in later:
            if e[STATE] is None:
                return False
        iu = est._slots['_u']
        if later[0][KIND] == MEASUREMENT:         # the input held at the command's stamp
            u_old = later[0][STATE][iu]
        elif pos and entries[pos - 1][STATE] is not None:
            u_old = entries[pos - 1][STATE][iu]
        else:
            return False
        u_new = est.check_input(entry[VALUE])
        shifted = shifted_states(est, entry[STAMP], u_new, u_new - u_old, [
            (e[STAMP], e[ROWS] if e[KIND] == MEASUREMENT else None, e[STATE])
            for e in later])
        revised = []
        for e, (state, x, residual, S) in zip(later, shifted):
            e[STATE] = state
            if x is not None:
                e[ESTIMATE], e[RESIDUAL], e[INNOVATION_COV] = x, residual, S
                revised.append((e[TAG], x, residual, S))
        est._restore_shifted(later[-1][STATE])   # the estimator was at the newest entry
        entries.insert(pos, entry)                # no state: a rewind applies it again
        if revised:
            self.revised = revised
        self.rewinds += 1
        self.superposed += 1
        return True

    def _superpose_head(self, entry):
        """
        Insert a command just before the newest entry, a measurement: shift the estimator.

        The closed loop's command a step late (most of them in P2): the state after the
        measurement is the estimator's own, and the input held at the command's stamp is
        the estimator's input (the measurement did not change it). So nothing saved is
        needed, and no dense checkpoints are turned on for it: the estimator is moved as
        :meth:`_superpose` moves a saved state, and the measurement's checkpoint, if it
        has one, saved again. Raises, changing nothing, for a bad input.
        """
        est = self._est
        entries = self._entries
        last = entries[-1]
        u_new = est.check_input(entry[VALUE])
        # the live parts, not copies: shifted_states makes new arrays of those it moves
        (state, x, residual, S), = shifted_states(
            est, entry[STAMP], u_new, u_new - est._u,
            [(last[STAMP], last[ROWS], est._state_values(est))])
        est._restore_shifted(state)
        if last[STATE] is not None:
            last[STATE] = est.save_state()
        last[ESTIMATE], last[RESIDUAL], last[INNOVATION_COV] = x, residual, S
        self.revised = [(last[TAG], x, residual, S)]
        entries.insert(len(entries) - 1, entry)   # no state: a rewind applies it again
        self.rewinds += 1
        self.superposed += 1

    def _rewind_one(self, entry, state):
        """
        Insert an entry just before the newest one, from the checkpoint before that one.

        The same calls on the same states as :meth:`_rewind` from a checkpoint makes
        (the result is the same to the last bit), but only the newest entry is applied
        again. Its checkpoint, if it has one, stays one (the new entry gets none).
        """
        est = self._est
        entries = self._entries
        last = entries[-1]
        est.restore_state(state)                  # copied: the checkpoint stays as it was
        try:
            self._apply(entry, False)
        except Exception:
            # a bad message changes nothing: the newest entry again, on the same state
            est.restore_state(state)
            self._apply(last, last[STATE] is not None)
            raise
        self._apply(last, last[STATE] is not None)
        if last[KIND] == MEASUREMENT:
            self.revised = [(last[TAG], last[ESTIMATE], last[RESIDUAL], last[INNOVATION_COV])]
        if last[STATE] is None:
            self._since += 1
        self.rewinds += 1
        self.reapplied += 1
        entries.insert(len(entries) - 1, entry)

    def _find_checkpoints(self):
        """List the entries with a state again (after a rewind moved the checkpoints)."""
        self._checkpoints = deque(e for e in self._entries if e[STATE] is not None)
