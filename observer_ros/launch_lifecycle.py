# observer_ros.launch_lifecycle: launch actions for the package's managed nodes and runs.
"""
Launch actions of ``launch/*.launch.py``: managed nodes brought up in order, runs that end.

:class:`BringUp` takes the managed nodes (the observer, then the compensator) through
``configure`` in order, then ``activate`` in order, by their ``change_state`` services (as
nav2's lifecycle manager does), and then starts what waits for them (the plant simulator).
A transition that fails stops the launch with an error naming the node (``ros2 launch``
exits 1; the node's own log line says why). With ``autostart:=false`` it changes nothing:
it waits until ``ros2 lifecycle set`` has made every node active, then starts the rest.

:func:`exit_handlers` make a run end as a user expects: when the simulator finishes its
run the launch shuts down (every node stopped, the bag closed), and a node that exits
with a status other than 0 (a file it cannot use, a crash) stops the launch with an error
(exit status 1) instead of leaving the others running.

"""

import threading
import time

from launch.action import Action
from launch.actions import EmitEvent, RegisterEventHandler
from launch.event import Event
from launch.event_handler import EventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
import launch.logging
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState

__all__ = ['BringUp', 'NodesActive', 'exit_handlers', 'node_path']

# s: how often a wait looks whether the launch is shutting down; how often, with
# autostart:=false, the nodes' states are asked
POLL = 0.5
# s: a state asked for and not answered by then is asked again (an answer lost)
ANSWER_WITHIN = 10.0
NO_ANSWER = object()


def node_path(namespace, name):
    """Return a node's full name: ``/sub2/observer``, ``/observer``."""
    namespace = namespace.strip('/')
    return f'/{namespace}/{name}' if namespace else f'/{name}'


class NodesActive(Event):
    """Every node of a :class:`BringUp` is active."""

    name = 'observer_ros.NodesActive'

    def __init__(self, bring_up):
        super().__init__()
        self.bring_up = bring_up


class BringUp(Action):
    """
    Configure, then activate, managed nodes in order; then start ``then``.

    Parameters
    ----------
    nodes : sequence of str
        The nodes' full names (:func:`node_path`), in the order they come up.
    autostart : bool
        False: no transition is asked for; ``then`` starts once every node is active.
    then : sequence of launch.Action
        Started once every node is active.

    """

    def __init__(self, nodes, autostart=True, then=(), **kwargs):
        super().__init__(**kwargs)
        self.nodes = list(nodes)
        self.autostart = autostart
        self.then = list(then)
        self._logger = launch.logging.get_logger('observer_ros')

    def execute(self, context):
        """Register what starts ``then``, and bring the nodes up from a thread."""
        from launch_ros.ros_adapters import get_ros_node    # the launch's own ROS node
        node = get_ros_node(context)
        clients = {name: (node.create_client(ChangeState, f'{name}/change_state'),
                          node.create_client(GetState, f'{name}/get_state'))
                   for name in self.nodes}
        context.register_event_handler(EventHandler(
            matcher=lambda event: isinstance(event, NodesActive) and event.bring_up is self,
            entities=self.then))
        context.add_completion_future(context.asyncio_loop.run_in_executor(
            None, self._run, context, clients))
        return None

    def _run(self, context, clients):
        if self.autostart:
            for transition, label in ((Transition.TRANSITION_CONFIGURE, 'configure'),
                                      (Transition.TRANSITION_ACTIVATE, 'activate')):
                for name in self.nodes:
                    response = self._call(context, clients[name][0], ChangeState.Request(
                        transition=Transition(id=transition)))
                    if response is None:        # the launch is shutting down
                        return
                    if not response.success:
                        raise RuntimeError(f'{name}: the {label} transition failed (its log '
                                           'says why)')
                    self._logger.info(f'{name}: {label}d')
        else:
            self._logger.info(f'autostart:=false: {", ".join(self.nodes)} wait unconfigured '
                              f'for `ros2 lifecycle set NODE configure`, then activate')
            for name in self.nodes:
                while True:
                    # a lost answer (a busy host: 'failed to send response') is asked again
                    response = self._call(context, clients[name][1], GetState.Request(),
                                          answer_within=ANSWER_WITHIN)
                    if response is None:
                        return
                    if response is NO_ANSWER:
                        continue
                    if response.current_state.id == State.PRIMARY_STATE_ACTIVE:
                        break
                    if self._wait(context, POLL):
                        return
        context.asyncio_loop.call_soon_threadsafe(context.emit_event_sync, NodesActive(self))

    @staticmethod
    def _wait(context, seconds):
        """Wait; return True when the launch is shutting down."""
        event = threading.Event()
        event.wait(seconds)
        return context.is_shutdown

    def _call(self, context, client, request, answer_within=None):
        """
        Call a service once it is up; None when the launch shuts down meanwhile.

        ``answer_within`` s: NO_ANSWER when no answer came by then (else it is waited for).
        """
        try:
            while not client.wait_for_service(timeout_sec=POLL):
                if context.is_shutdown:
                    return None
            done = threading.Event()
            future = client.call_async(request)
            future.add_done_callback(lambda _: done.set())
            asked = time.monotonic()
            while not done.wait(POLL):
                if context.is_shutdown:
                    future.cancel()
                    return None
                if answer_within is not None and time.monotonic() - asked > answer_within:
                    future.cancel()
                    return NO_ANSWER
            return future.result()
        except Exception:   # noqa: BLE001 - the launch's node goes away as it shuts down
            if context.is_shutdown:
                return None
            raise


def exit_handlers(nodes, simulator=None):
    """
    Return the handlers that end a run: the simulator done, or a node that failed.

    Parameters
    ----------
    nodes : sequence of launch_ros.actions.Node
        Every node process of the launch (the simulator among them).
    simulator : launch_ros.actions.Node, optional
        Its exit with status 0 (the run complete) shuts the launch down.

    """
    def on_exit(event, context):
        code = event.returncode
        if code != 0:
            raise RuntimeError(f'{event.process_name} exited with status {code} (its log '
                               'above says why)')
        if event.action is simulator and not context.is_shutdown:
            return [EmitEvent(event=Shutdown(reason='the simulator completed its run'))]
        return None
    return [RegisterEventHandler(OnProcessExit(target_action=node, on_exit=on_exit))
            for node in nodes]
