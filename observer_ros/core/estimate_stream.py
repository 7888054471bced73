# observer_ros.core.estimate_stream: which estimates the compensator follows.
"""
Which estimates the compensator follows when two streams may share ``state/estimate``.

Jazzy's rclpy gives no publisher GID, and its events executor refuses callbacks that
take the message info (where the writer's sequence number is): the stream is told by
its values. With two publishers known, or with a warm standby observer (a second
publisher's first estimates can come before its match), an estimate belongs to the
stream followed when it is within :data:`CONSISTENCY_TOL` of a state's scale of the
model's prediction from the last estimate followed, or of the standby's estimate at its
stamp (a standby beyond the divergence envelope is no reference); one that fits neither
is another stream's (a second observer not yet converged): ignored and counted. The
standby does not veto the stream followed: an estimate that continues it while the
standby is further away is followed, the disagreement counted
(``standby_disagreements``, a WARN), and while they disagree no lag hands the loop over
to the standby (a starved compensator's standby can be the one that is wrong); the
stream followed falling silent still does (``controller.stale_timeout``).

No ROS here.
"""

import numpy as np

from .loop_status import ERROR, WARN

__all__ = ['CONSISTENCY_TOL', 'EstimateStream', 'within']

# An estimate this far (in units of each state's scale) from the reference belongs to
# another stream; the observer's must come this close to the standby's to be followed.
CONSISTENCY_TOL = 0.1


def within(x, ref, scale, tol):
    """Tell whether x is within tol of each state's scale of the reference ref."""
    return bool(np.max(np.abs(np.asarray(x) - ref) / scale) <= tol)


class EstimateStream:
    """
    The reports of the stream followed: estimates ignored, a standby that disagrees.

    Parameters
    ----------
    count, log : callable
        ``count(key)``, ``log(level, text)``: the supervisor's counters and log lines.

    Attributes
    ----------
    other : int
        Estimates of another stream ignored since the last report.
    standby_agrees : bool
        Whether the standby agreed with the last estimate of the stream followed.

    """

    def __init__(self, count, log):
        self._count, self._log = count, log
        self.other = 0
        self._said = False
        self.standby_agrees = True

    def belongs(self, x, ref, predict, scale):
        """
        Tell whether an estimate belongs to the stream followed.

        Parameters
        ----------
        x : sequence of float
            The estimate.
        ref : ndarray or None
            The standby's estimate at its stamp; None without a usable one (not warm,
            beyond the envelope).
        predict : callable
            ``predict()`` -> the model's prediction at its stamp from the last estimate
            followed, or None (none yet, or too far back); called only when needed.
        scale : ndarray
            Each state's scale.

        """
        if ref is not None and within(x, ref, scale, CONSISTENCY_TOL):
            self.standby_agrees = True
            return True
        predicted = predict()
        if predicted is None:
            return ref is None
        fits = within(x, predicted, scale, CONSISTENCY_TOL)
        if fits and ref is not None:
            self.standby_disagrees()
        return fits

    def ignore(self, text):
        """Ignore an estimate of another stream: counted, said once (ERROR); return None."""
        self._count('other_stream_estimates')
        if not self.other and not self._said:
            self._log(ERROR, f'{text}, and the others like it')
            self._said = True
        self.other += 1

    def standby_disagrees(self):
        """Note an estimate of the stream followed the standby disagrees with (said once)."""
        self._count('standby_disagreements')
        if self.standby_agrees:
            self._log(WARN, f"standby observer: more than {CONSISTENCY_TOL:g} of a state's "
                      'scale from the estimates followed; no hand-over to it until they '
                      'agree again')
        self.standby_agrees = False

    def report(self):
        """Return the estimates of another stream ignored since the last report; start anew."""
        other, self.other = self.other, 0
        if not other:
            self._said = False
        return other
