# observer_ros.core.estimators.entries: the layout of the history's entries.
"""
One entry of :class:`~.history.History` per message: a list, indexed by the fields below.

Shared by the history and its rewinding (:mod:`.rewind`).

"""

__all__ = ['MEASUREMENT', 'COMMAND', 'STAMP', 'KIND', 'VALUE', 'ROWS', 'TAG', 'STATE',
           'ESTIMATE', 'RESIDUAL', 'INNOVATION_COV', 'new_entry']

MEASUREMENT, COMMAND = 0, 1

# An entry of the history is a list (cheaper to make than an object, per message):
# the message's stamp, kind, value, rows and tag, then what applying it gave: the
# estimator's state after it (a checkpoint, or None), and for a measurement the estimate
# at its stamp, its residual and S (for the call itself and :attr:`History.revised`; the
# fast path of :meth:`History.correct` does not keep them). At one stamp the
# measurements come before the commands, and messages of one kind in the order they
# arrived.
STAMP, KIND, VALUE, ROWS, TAG, STATE, ESTIMATE, RESIDUAL, INNOVATION_COV = range(9)


def new_entry(t, kind, value, rows, tag):
    """Return a new entry: the message's fields, nothing applied yet."""
    return [t, kind, value, rows, tag, None, None, None, None]
