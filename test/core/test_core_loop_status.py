# test_core_loop_status: the words and level of the compensator's report.
"""The compensator's report: the worst thing first, then the mode."""

from observer_ros.core.loop_status import ERROR, OK, status_message, WARN
import pytest


def test_the_worst_thing_is_said_first():
    level, message = status_message('closed', duplicates=['/state/estimate (2 publishers)'],
                                    other=3, refused='command nan: safe command sent instead')
    assert level == ERROR
    assert message.startswith('more than one publisher: /state/estimate (2 publishers)')
    assert '3 estimates of another ignored' in message
    level, message = status_message('closed', refused='command nan', too_late=2)
    assert (level, message) == (ERROR, 'command nan')
    level, message = status_message('stale', too_late=2, standby=True, history=0.25)
    assert level == ERROR and message == ('2 estimates later than observer.history_length '
                                          '(0.25 s): the standby observer closes the loop')
    level, message = status_message('closed', problem='diverging: x beyond 1e+06')
    assert (level, message) == (ERROR, 'diverging: x beyond 1e+06')


@pytest.mark.parametrize('mode, standby, level, words', [
    ('waiting', False, WARN, 'waiting for the estimate'),
    ('closed', False, OK, 'closing the loop'),
    ('stale', True, ERROR, 'the standby observer closes the loop'),
    ('stale', False, ERROR, 'safe command (predict)'),
    ('resync', True, WARN, 'not yet agreeing with the standby observer'),
    ('resync', False, ERROR, 'the observer settling: safe command (predict)'),
    ('recover', False, ERROR, 'OK after 0.4 s'),
])
def test_each_mode_is_said(mode, standby, level, words):
    got, message = status_message(mode, standby=standby, safe_mode='predict', settle=0.4)
    assert got == level and words in message, message
