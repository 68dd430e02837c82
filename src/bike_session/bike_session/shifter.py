"""``./bike shift N``: press a running bike's virtual shifter (N gears up, -N down).

One std_msgs/Int8 on ``/<namespace>/shift``, which the session node turns into the gear of
its next Commands (bike_session.session_node, bike_controller.modes: virtual shifting). The
ros2 command line is not on PyPI (ROS2_ON_PIP.md), so this is the pip install's
``ros2 topic pub --once /bike/shift std_msgs/msg/Int8 "{data: N}"``. The run's DDS domain is
the one ``./bike run`` printed (``--domain``, else ROS_DOMAIN_ID)."""
from __future__ import annotations

import os
import sys
import time

MATCH_TIMEOUT_S = 10.0       # discovery of the session's subscription
ACK_TIMEOUT_S = 2.0


def press(steps: int, namespace: str = "bike", domain: int | None = None,
          match_timeout_s: float = MATCH_TIMEOUT_S) -> int:
    """Publish one shift; 0 when the session's subscription acknowledged it, 1 when no
    session listens on the topic, 2 for a bad argument. Messages on stderr / stdout."""
    if not -127 <= steps <= 127 or steps == 0:
        print(f"error: gears must be a non-zero whole number in [-127, 127], got {steps}", file=sys.stderr)
        return 2
    if domain is None:
        from bike_session.domains import environment_problem
        if environment_problem():
            # ROS_DOMAIN_ID=999 was refused as '--domain must be in [0, 232]', an option not given
            print(f"error: {environment_problem()}; or give --domain", file=sys.stderr)
            return 2
        domain = int(os.environ.get("ROS_DOMAIN_ID") or 0)
    if not 0 <= domain <= 232:
        print(f"error: --domain must be in [0, 232], got {domain}", file=sys.stderr)
        return 2
    from bike_session.cli import namespace_problem
    problem = namespace_problem(namespace)
    if problem:
        # create_publisher would raise InvalidTopicNameException (a traceback)
        print(f"error: {problem}", file=sys.stderr)
        return 2
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Int8

    topic = f"/{namespace.strip('/')}/shift" if namespace.strip("/") else "/shift"
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain, args=["--ros-args", "--disable-rosout-logs"])
    try:
        node = rclpy.create_node("bike_shift", context=context)
        pub = node.create_publisher(Int8, topic, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        end = time.monotonic() + match_timeout_s
        while pub.get_subscription_count() == 0 and time.monotonic() < end:
            time.sleep(0.05)
        if pub.get_subscription_count() == 0:
            print(f"error: no session listens on {topic} in DDS domain {domain} (is a run going? `./bike run` "
                  f"prints its ROS_DOMAIN_ID; give it with --domain)", file=sys.stderr)
            return 1
        time.sleep(0.2)                  # the reader's side of the match, before the sample
        pub.publish(Int8(data=int(steps)))
        if not pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S)):
            print(f"error: the shift on {topic} was not acknowledged within {ACK_TIMEOUT_S:g} s", file=sys.stderr)
            return 1
        print(f"[bike] shift {steps:+d} sent on {topic} (domain {domain}); the session logs the new gear")
        node.destroy_node()
        return 0
    finally:
        rclpy.try_shutdown(context=context)
