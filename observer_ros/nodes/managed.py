# observer_ros.nodes.managed: the observer and the compensator as managed (lifecycle) nodes.
"""
Managed nodes (``rclpy.lifecycle``), as nav2 and ros2_control run theirs.

The observer and the compensator go through the ROS 2 lifecycle states; ``ros2 lifecycle
get /observer`` shows the state and ``ros2 lifecycle set /observer configure`` (or
``activate``, ``deactivate``, ``cleanup``, ``shutdown``) changes it:

- **unconfigured**: the parameters are declared and the node's services are up (the
  lifecycle's, the parameters', the observer's reset); nothing else. A vehicle parameter
  may be changed freely here (the file is checked when the node is configured).
- **configure**: the vehicle file is read and verified by the loader, the design made,
  the publishers created. A file the node cannot use fails the transition (the reason is
  logged as an error) and the node stays unconfigured: fix a parameter, configure again.
- **activate**: the subscriptions and the timers are created: the node estimates (the
  observer) or commands (the compensator) and reports on /diagnostics.
- **deactivate**: the compensator first sends its safe command; then the subscriptions and
  timers are destroyed (an inactive node is not in the graph as a reader). The publishers
  stay.
- **cleanup**: the publishers are destroyed, the design forgotten.
- **shutdown** (from any state): deactivate and clean up as needed. A node process that is
  stopped (SIGINT, SIGTERM) takes this transition before it exits.

With ``autostart`` (true by default) the node configures and activates itself when it is
built: ``ros2 run observer_ros observer --ros-args --params-file ...`` works as ever, and
a file it cannot use stops it before anything starts (exit status 2). The launch files
start the nodes with ``autostart: false`` and bring them up in order themselves
(``observer_ros.launch_lifecycle``).

"""

import traceback

from rclpy.lifecycle import LifecycleNodeMixin, TransitionCallbackReturn

from .common import VehicleNode
from ..core.errors import ObserverError

__all__ = ['ManagedVehicleNode', 'SUCCESS', 'FAILURE', 'ERROR']

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
ERROR = TransitionCallbackReturn.ERROR


def _entities(node):
    """Return what a node has made that a transition may have to destroy, by kind."""
    return {'publishers': set(node.publishers), 'subscriptions': set(node.subscriptions),
            'timers': set(node.timers),
            'parameter_callbacks': list(node._on_set_parameters_callbacks)}    # noqa: SLF001


class ManagedVehicleNode(LifecycleNodeMixin, VehicleNode):
    """
    A vehicle node with the ROS 2 lifecycle: configure, activate, deactivate, cleanup.

    A subclass builds in :meth:`configure_vehicle` (the design, the publishers, its
    parameter callback) and :meth:`activate_vehicle` (its subscriptions and timers), and
    may act in :meth:`deactivate_vehicle` before they go; what each made is destroyed by
    this class when the transition back comes. ``self.vehicle`` is the vehicle while
    configured, else None; ``self.active`` is True while active.

    """

    def __init__(self, node_name, own_parameters=()):
        VehicleNode.__init__(self, node_name, tuple(own_parameters) + ('autostart',),
                             load=False)
        LifecycleNodeMixin.__init__(self)
        self._guard_change_state()
        self.active = False
        self.transition_error = None        # why the last transition failed
        self._made = {}                     # transition -> what it made
        self._starting = False
        if self.param('autostart'):
            self.start()

    # -- what a subclass does -------------------------------------------------------------
    def configure_vehicle(self):
        """Design and create the publishers (``self.vehicle`` is loaded); raise to refuse."""

    def activate_vehicle(self):
        """Create the subscriptions and timers: start estimating or commanding."""

    def deactivate_vehicle(self):
        """Act before the subscriptions and timers are destroyed (a safe command)."""

    # -- autostart ------------------------------------------------------------------------
    def start(self):
        """Configure and activate now; raise ObserverError with the reason if it fails."""
        self._starting = True
        try:
            for transition in (self.trigger_configure, self.trigger_activate):
                if transition() != SUCCESS:
                    raise ObserverError(self.transition_error or
                                        f'{self.get_name()}: {transition.__name__} failed')
        finally:
            self._starting = False

    def finish(self):
        """Take the shutdown transition from any primary state (the process is ending)."""
        if self._state_machine.current_state[1] in ('unconfigured', 'inactive', 'active'):
            self.trigger_shutdown()

    # -- the transitions ------------------------------------------------------------------
    def on_configure(self, state):
        """Read and verify the vehicle file, design, create the publishers."""
        return self._transition('configure', self._configure)

    def on_activate(self, state):
        """Create the subscriptions and timers."""
        return self._transition('activate', self._activate)

    def on_deactivate(self, state):
        """Let the subclass act (the safe command), then destroy what activate made."""
        return self._transition('deactivate', self._deactivate)

    def on_cleanup(self, state):
        """Destroy what configure made; forget the vehicle."""
        return self._transition('cleanup', self._cleanup)

    def on_shutdown(self, state):
        """Deactivate and clean up, as far as the node got."""
        def shutdown():
            if self.active:
                self._deactivate()
            self._cleanup()
        return self._transition('shutdown', shutdown)

    def on_error(self, state):
        """Forget everything after a transition that raised: back to unconfigured."""
        self.active = False
        self._undo('activate')
        self._undo('configure')
        self.vehicle = None
        return SUCCESS

    def _guard_change_state(self):
        """
        Refuse a ChangeState request the current state has no transition for.

        rclpy's handler raises on a transition id that is not valid from the current state
        (``Transition is not registered``; a label is checked), and the exception ends the
        process: such a request is answered ``success: false``, logged and counted
        (``refused_transitions``), and the node goes on in its state.
        """
        service = getattr(self, '_service_change_state', None)
        if service is None:
            return
        handle = service.callback

        def change_state(request, response):
            transition = request.transition
            valid = {t[0] for t in self._state_machine.available_transitions}
            if not transition.label and transition.id not in valid:
                state = self._state_machine.current_state[1]
                self.count('refused_transitions')
                self.get_logger().warning(
                    f'lifecycle transition {transition.id} refused: not available from '
                    f'the state {state!r}')
                response.success = False
                return response
            return handle(request, response)

        service.callback = change_state

    def _transition(self, name, work):
        """Run a transition; a failure is logged with its reason (rclpy would hide it)."""
        self.transition_error = None
        try:
            work()
        except (ObserverError, ValueError) as err:
            self.transition_error = str(err)
            if not self._starting:      # autostart: reported once, as the process ends
                self.get_logger().error(f'{name} failed: {err}')
            return FAILURE
        except Exception as err:    # noqa: BLE001 - a bug: its traceback, errorprocessing
            self.transition_error = f'{name}: {type(err).__name__}: {err}'
            self.get_logger().error(f'{name} failed:\n{traceback.format_exc()}')
            return ERROR
        return SUCCESS

    def _configure(self):
        before = _entities(self)
        try:
            self.vehicle = self.load_vehicle()
            self.configure_vehicle()
        except BaseException:
            self._made['configure'] = self._new_since(before)
            self._undo('configure')
            self.vehicle = None
            raise
        self._made['configure'] = self._new_since(before)

    def _activate(self):
        before = _entities(self)
        try:
            self.activate_vehicle()
        except BaseException:
            self._made['activate'] = self._new_since(before)
            self._undo('activate')
            raise
        self._made['activate'] = self._new_since(before)
        self.active = True

    def _deactivate(self):
        try:
            self.deactivate_vehicle()
        finally:
            self.active = False
            self._undo('activate')

    def _cleanup(self):
        self._undo('configure')
        self.vehicle = None

    def _new_since(self, before):
        now = _entities(self)
        made = {kind: now[kind] - before[kind]
                for kind in ('publishers', 'subscriptions', 'timers')}
        made['parameter_callbacks'] = [cb for cb in now['parameter_callbacks']
                                       if cb not in before['parameter_callbacks']]
        return made

    def _undo(self, transition):
        """Destroy what a transition made (and what was made while in its state)."""
        made = self._made.pop(transition, None)
        if not made:
            return
        for callback in made['parameter_callbacks']:
            self.remove_on_set_parameters_callback(callback)
        for sub in made['subscriptions']:
            self.topic_watch.forget(sub)
            self.callback_watch.forget(sub)
            self.destroy_subscription(sub)
        for timer in made['timers']:
            self.destroy_timer(timer)
        for pub in made['publishers']:
            self.destroy_publisher(pub)

    # -- VehicleNode ----------------------------------------------------------------------
    def _diagnostics_period(self):
        """Return the diagnostics period while active (the callback watch reports then)."""
        return VehicleNode._diagnostics_period(self) if self.active else None
