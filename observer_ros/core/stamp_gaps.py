# observer_ros.core.stamp_gaps: messages missed, read from the gaps between a sensor's stamps.
"""
How many of a sensor's messages were missed, from the gaps between its stamps.

A gap of ``g`` periods between two consecutive stamps of a sensor leaves ``g - 1``
messages owed. A late message owes as much as a lost one, but the message after it makes
up for it (a publisher starved of CPU stamps one message late, then the next on time or
at once); a lost message is never made up. So a gap's messages are counted as missed only
when the next message still leaves them owed: with :class:`MissedStamps`, a publisher's
jitter (up to a period either way) is no missed message, and a lost message is counted one
message later. No credit is banked: a sensor faster than its period (or a burst) does not
hide a later loss. A message older than the sensor's newest stamp (reordered) makes up one
message; a gap of :data:`PAUSE_PERIODS` periods or more is a pause, not missed messages.

No rclpy here: the observer node feeds it each stamp newer than the sensor's newest (and
the reordered ones), and counts what it returns as missed in its load meter.

"""

__all__ = ['PAUSE_PERIODS', 'MissedStamps']

# a gap of this many periods or more is a pause (the sensor stopped), not missed messages
PAUSE_PERIODS = 100.0
# periods: what float stamps leave of an exact multiple of the period (0.3 / 0.05 - 1)
_ROUNDING = 1e-6


class MissedStamps:
    """
    Count a sensor's missed messages from the gaps between its stamps.

    Parameters
    ----------
    period : float
        The sensor's period (s), > 0.

    Attributes
    ----------
    owed : float
        Messages the gaps so far leave owed (periods), not yet counted.

    """

    __slots__ = ('period', 'owed')

    def __init__(self, period):
        period = float(period)
        if not period > 0.0:
            raise ValueError(f'period must be > 0 s, got {period!r}')
        self.period = period
        self.owed = 0.0

    def gap(self, gap):
        """
        Note a message ``gap`` s after the sensor's newest stamp; return the messages missed.

        ``gap <= 0`` is a reordered message (older than the newest stamp): it makes up
        one message owed.
        """
        before = self.owed
        if gap <= 0.0:
            owed = before - 1.0
        else:
            periods = gap / self.period
            if periods >= PAUSE_PERIODS:    # a pause: nothing missed, nothing owed
                self.owed = 0.0
                return 0
            owed = before + periods - 1.0
        # counted only what the gap before left owed and this message did not make up
        low = min(before, owed) + _ROUNDING
        missed = int(low) if low >= 1.0 else 0
        self.owed = max(0.0, owed - missed)
        return missed
