# The seeds' plants the tests share, typed once.
"""
The submarine (seed 000) and the cart-pendulum (seed 002), as the core's ``Plant``.

The matrices are those of config/submarine.yaml and config/cart_pendulum.yaml, which
test_vehicle.py checks against these.
"""

import numpy as np
from observer_ros.core.model import Plant

# Seed 000 submarine pitch model: states [theta, w, q], input the stern-plane angle delta.
SUBMARINE_A = ((0.0, 0.0, 1.0), (0.0135, -0.322, -0.7102), (-0.036, 0.126, -0.7395))
SUBMARINE_B = ((0.0,), (0.0322,), (-0.0857,))
GYRO_C = ((0.0, 0.0, 1.0),)                             # a rate gyro on q
GYRO_PITCH_C = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0))       # the gyro (output 0), pitch (1)
GYRO, PITCH = (0,), (1,)                                # the rows of each sensor

# Seed 002 inverted pendulum on a cart: states [theta, x, theta', x'], input the force.
CART_A = ((0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0), (10.78, 0.0, 0.0, 0.0),
          (-0.98, 0.0, 0.0, 0.0))
CART_B = ((0.0,), (0.0,), (-1.0,), (1.0,))


def submarine(C=GYRO_C, **names):
    """Return the submarine, states [theta, w, q]; by default a rate gyro on q."""
    names.setdefault('state_names', ('theta', 'w', 'q'))
    names.setdefault('input_names', ('delta',))
    return Plant(SUBMARINE_A, SUBMARINE_B, np.array(C, dtype=float), None, **names)


def two_sensor_submarine():
    """Return the submarine with a gyro (q, output 0) and a pitch sensor (theta, output 1)."""
    return submarine(GYRO_PITCH_C, output_names=('q', 'theta'))


def cart(C=((0.0, 1.0, 0.0, 0.0),)):
    """Return the cart-pendulum; by default C measures the cart's position x."""
    return Plant(CART_A, CART_B, np.array(C, dtype=float), None,
                 state_names=('theta', 'x', 'theta_dot', 'x_dot'))
