# observer_ros.core.loop_command: what the loop supervisor hands the compensator to send.
"""A command the compensator sends (its values, its stamp, what it answers) and its gate."""

__all__ = ['Command', 'command_refusal']


class Command:
    """
    A command to send: ``u`` (m floats), stamped ``t``.

    ``answers``: it answers the estimate (or measurement) just given, so it carries that
    message's stamp as it is; ``marked``: it answers nothing (a safe command for a stale
    estimate; lock-step does not take it for an answer); ``source``: ``observer``,
    ``standby`` or ``safe``.
    """

    __slots__ = ('u', 't', 'answers', 'marked', 'source')

    def __init__(self, u, t, answers=False, marked=False, source='observer'):
        self.u, self.t, self.answers, self.marked, self.source = u, t, answers, marked, source

    def __repr__(self):
        return (f'Command(u={list(self.u)}, t={self.t}, answers={self.answers}, '
                f'marked={self.marked}, source={self.source!r})')


def command_refusal(law, u_envelope, u):
    """
    Return why the command u must not be sent, or None when it may.

    ``law`` (:class:`~.control_law.ControlLaw`) judges it against the limits; without
    limits ``u_envelope`` (:class:`~.health.Envelope`) bounds it.
    """
    reason = law.problem(u)
    if reason is None and not law.limited and not u_envelope.inside(u):
        bound = u_envelope.bound
        reason = (f'{list(u)} beyond the bound +-{bound.tolist()} (100 x K applied to '
                  "the file's state scale; no controller.u_min/u_max)")
    return reason
