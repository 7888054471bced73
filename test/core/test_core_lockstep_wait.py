# test_core_lockstep_wait: the lock-step observer's wait for its command (no DDS).
"""core.lockstep_wait.CommandWait: answers, re-sends, giving up, and a hold of the process."""

from observer_ros.core.lockstep_wait import (CommandWait, DEFERRED, GAVE_UP, RESEND,
                                             RESEND_AFTER, WATCH_GAP, WATCH_PERIOD)

TIMEOUT = 2.0       # the simulator's command_timeout


def _checks(wait, start, end):
    """Run the watchdog every WATCH_PERIOD from start to end; return the verdicts."""
    out, now = [], start
    while now <= end + 1e-9:
        out.append(wait.check(now, TIMEOUT))
        now += WATCH_PERIOD
    return out


def test_the_command_stamped_as_the_estimate_ends_the_wait():
    wait = CommandWait()
    wait.published(2.35, 10.0)
    assert wait.pending == 1
    assert not wait.answered(2.30)          # an older command answers nothing
    assert wait.pending == 1
    assert wait.answered(2.35) and wait.pending == 0
    assert not wait.answered(2.35)          # a second copy: nothing pending
    wait.published(2.40, 10.1)
    wait.published(2.40, 10.2)              # the same estimate re-published (a duplicate)
    assert not wait.answered(2.40) and wait.answered(2.40)


def test_an_unanswered_estimate_is_sent_again_then_given_up():
    wait = CommandWait()
    assert wait.check(10.0, TIMEOUT) is None            # nothing pending
    wait.published(1.0, 10.0)
    verdicts = _checks(wait, 10.1, 12.5)
    first_resend = verdicts.index(RESEND)
    assert first_resend * WATCH_PERIOD + 0.1 > RESEND_AFTER
    assert verdicts.count(GAVE_UP) == 1 and DEFERRED not in verdicts
    assert verdicts[verdicts.index(GAVE_UP) + 1:] == [None] * (len(verdicts) - 1 -
                                                               verdicts.index(GAVE_UP))
    assert wait.pending == 0


def test_a_hold_of_the_process_restarts_the_wait():
    """
    Held off the CPU for 2 s while an estimate waits for its command.

    At the resume the watchdog's timer can run twice before the command, which waits in
    the process's queue, is taken: neither check may give up, or the observer corrects
    with the next measurement before it has that command.
    """
    wait = CommandWait()
    wait.published(2.35, 10.0)
    assert _checks(wait, 10.1, 10.15) == [None]
    resume = 10.1 + TIMEOUT + 0.5                       # no check ran meanwhile
    assert wait.check(resume, TIMEOUT) is DEFERRED
    assert wait.check(resume + WATCH_PERIOD, TIMEOUT) is None
    assert wait.check(resume + 2 * WATCH_PERIOD, TIMEOUT) is None
    assert wait.check(resume + 3 * WATCH_PERIOD, TIMEOUT) is RESEND
    assert wait.pending == 1 and wait.answered(2.35)
    # a hold while nothing waits: nothing to judge, nothing deferred
    assert wait.check(resume + 10.0, TIMEOUT) is None
    # a process that keeps running past the timeout after the hold gives up as before
    wait.published(2.40, resume + 10.0)
    verdicts = _checks(wait, resume + 10.0 + WATCH_GAP + 0.1, resume + 13.0)
    assert verdicts[0] is DEFERRED and GAVE_UP in verdicts
