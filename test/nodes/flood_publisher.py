# A process that publishes sensor_msgs/Imu as fast as it can: a measurement flood.
"""
Flood a topic with Imu messages stamped with the wall clock, as fast as Python publishes.

Run as ``python test/nodes/flood_publisher.py TOPIC SECONDS``: it waits until the topic has a
subscriber, publishes for SECONDS, then prints ``published N rate R`` (messages/s).
Used by test_nodes_flood.py and benchmarks/flood_observer.py (a separate process, so the
test's probe stays responsive).
"""

import sys
import time
import warnings


def main(topic, seconds):
    """Publish Imu on ``topic`` for ``seconds`` s; return the number published."""
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Imu
    rclpy.init()
    node = rclpy.create_node('flood')
    pub = node.create_publisher(Imu, topic, qos_profile_sensor_data)
    while node.count_subscribers(topic) < 1:
        time.sleep(0.05)
    msg = Imu()
    msg.angular_velocity.y = 0.001
    count, start = 0, time.monotonic()
    end = start + seconds
    stamp = msg.header.stamp
    while time.monotonic() < end:
        now = time.time_ns()
        stamp.sec, stamp.nanosec = divmod(now, 1_000_000_000)
        pub.publish(msg)
        count += 1
    print(f'published {count} rate {count / (time.monotonic() - start):.0f}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return count


if __name__ == '__main__':
    main(sys.argv[1], float(sys.argv[2]))
