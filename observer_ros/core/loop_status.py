# observer_ros.core.loop_status: what the compensator's /diagnostics line says.
"""
The level and message of the compensator's report, from the loop supervisor's state.

The worst first: more than one publisher on a topic, estimates of another stream ignored,
a command refused, estimates later than the history, an implausible or diverging estimate,
then the supervisor's mode (:mod:`.loop_supervisor`).
"""

__all__ = ['OK', 'WARN', 'ERROR', 'status_message']

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2


def status_message(mode, duplicates=(), other=0, refused=None, too_late=0, problem=None,
                   standby=False, safe_mode='', history=0.0, settle=0.0):
    """
    Return ``(level, message)`` of the compensator's report.

    Parameters
    ----------
    mode : str
        The supervisor's mode: ``waiting``, ``closed``, ``stale``, ``resync``, ``recover``.
    duplicates : sequence of str
        ``"topic (N publishers)"`` for the node's topics with more than one.
    other : int
        Estimates of another stream ignored since the last report.
    refused : str or None
        The last command refused since the last report, said as it was logged.
    too_late : int
        Estimates later than ``observer.history_length`` since the last report.
    problem : str or None
        The implausible or diverging estimate in force.
    standby : bool
        Whether a standby observer closes the loop when the estimates do not.
    safe_mode : str
        The safe command's mode (predict or hold).
    history : float
        ``observer.history_length`` (s).
    settle : float
        The observer's settling time (s).

    """
    if duplicates:
        level = ERROR
        message = f'more than one publisher: {", ".join(duplicates)}'
        if other:
            message += (f'; following one estimate stream, {other} estimates of another '
                        'ignored')
    elif other:
        level = ERROR
        message = (f'{other} estimates ignored: they do not follow the stream followed '
                   "(the standby observer's estimate, or the model from the last one)")
    elif refused:
        level, message = ERROR, refused
    elif too_late:
        level = ERROR
        answer = 'the standby observer closes the loop' if standby \
            else f'safe command ({safe_mode})'
        message = (f'{too_late} estimates later than observer.history_length '
                   f'({history:g} s): {answer}')
    elif problem is not None:
        level, message = ERROR, problem
    elif mode == 'stale':
        level = ERROR
        message = ('estimate stale: the standby observer closes the loop'
                   if standby else
                   f'estimate stale: safe command ({safe_mode})')
    elif mode == 'resync':
        level = WARN if standby else ERROR
        message = ('estimates back, not yet agreeing with the standby observer: it '
                   'closes the loop' if standby else
                   'estimates back, the observer settling: safe command '
                   f'({safe_mode})')
    elif mode == 'recover':
        level = ERROR
        message = (f'recovering after an outage: closing the loop again, OK after '
                   f'{settle:g} s')
    elif mode == 'waiting':
        level, message = WARN, 'waiting for the estimate'
    else:
        level, message = OK, 'closing the loop'
    return level, message
