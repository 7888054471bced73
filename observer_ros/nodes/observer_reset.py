# observer_ros.nodes.observer_reset: re-initialise the observer on request (a service, a topic).
"""
Re-initialise the observer's estimate on request, as robot_localization's ``set_pose``.

- ``~/reset`` (``std_srvs/srv/Trigger``; ``/observer/reset``): back to the vehicle file's
  ``observer.initial_estimate``. The estimator and its history are forgotten; the next
  measurement starts the estimate again at its own stamp. ``ros2 service call
  /observer/reset std_srvs/srv/Trigger`` answers ``success: true`` and what it did; an
  observer that is not active answers ``success: false`` and its lifecycle state.
- ``~/set_state`` (``sensor_msgs/msg/JointState``; ``/observer/set_state``): start again
  from a given state. ``name`` lists the model's states (any order, each once), ``position``
  their values; ``header.stamp`` is the time of that state (0: the time of the next
  measurement). A message the node cannot use (a missing or unknown state, a value that is
  not finite, a malformed stamp) is refused and logged naming the field; the estimate goes on.

Each reset is logged and counted on /diagnostics (``reset_requests``, and
``estimator_resets`` with the node's own resets); the innovation health and the divergence
envelope start over with it.

"""

from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from .common import checked_stamp, STATE_QOS, vector_from_joint_state
from ..core.errors import ObserverError

__all__ = ['RESET_SERVICE', 'SET_STATE_TOPIC', 'ObserverReset']

RESET_SERVICE = '~/reset'
SET_STATE_TOPIC = '~/set_state'


class ObserverReset:
    """The observer's reset service and set_state topic; a mixin of ObserverNode."""

    def _init_reset(self):
        """Create the reset service (up in every lifecycle state)."""
        self._reset_srv = self.create_service(Trigger, RESET_SERVICE, self._on_reset)

    def _subscribe_set_state(self):
        """Subscribe to ``~/set_state`` (while active)."""
        self._set_state_sub = self.watched_subscription(
            JointState, SET_STATE_TOPIC, self._on_set_state, STATE_QOS, shed=False)

    def _on_reset(self, request, response):
        if not getattr(self, 'active', False):
            response.success = False
            response.message = (f'not active (lifecycle state '
                                f'{self._state_machine.current_state[1]}): nothing to reset')
            return response
        self._reset_to(None, None, 'reset service')
        response.success = True
        response.message = (f'estimate reset to observer.initial_estimate '
                            f'{self.estimator.x_hat.tolist()}; it starts again at the next '
                            'measurement')
        return response

    def _on_set_state(self, msg):
        topic = self.resolve_topic_name(SET_STATE_TOPIC)
        try:
            x = vector_from_joint_state(msg, self.vehicle.plant.state_names, topic)
            stamp = msg.header.stamp
            t = None if stamp.sec == 0 and stamp.nanosec == 0 else checked_stamp(stamp, topic)
        except (ObserverError, ValueError) as err:
            self.count('bad_set_state')
            self.get_logger().error(f'{err}; the estimate goes on',
                                    throttle_duration_sec=1.0)
            return
        self._reset_to(x, t, f'{topic}: state {x.tolist()} at ' +
                       ('the next measurement' if t is None else f'{t:.6f} s'))

    def _reset_to(self, x0, t0, why):
        """Start the estimate again from x0 at t0 (None: the file's, the next message)."""
        self.history.reset(x0, t0)
        self._health.restart()
        self._envelope.reset()
        self.count('reset_requests')
        self.count('estimator_resets')
        self.get_logger().info(f'estimator reset on request ({why})')
