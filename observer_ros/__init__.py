"""observer_ros: state estimators (Luenberger, reduced-order, Kalman) as ROS 2 nodes."""

__version__ = '0.1.0'
