"""What an rclpy executor costs per message taken: ``python -m csam_ros.bench.executors
[--rate HZ] [--seconds S] [--subscriptions N ...]``.

A publisher process sends ``tf2_msgs/TFMessage`` on ``/tf`` at ``--rate`` Hz (the rate of a
five-robot MR.CLAM replay's ``/tf`` and odometry together is about 700 Hz); a subscriber
process takes them raw, as the recorder does, with ``N - 1`` idle subscriptions beside it (the
recorder of a five-robot run holds about 40), spinning each executor in turn by
``spin_once``. Printed per executor and ``N``: the messages taken and the subscriber's CPU
time per message (``time.process_time``), which is what the executor adds to a node's work.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

SUBSCRIBER = """
import sys, time, rclpy
from rclpy.qos import QoSProfile
from tf2_msgs.msg import TFMessage
from csam_ros.nodes import common
import os
os.environ[common.EXECUTOR_VARIABLE] = sys.argv[1]
subscriptions, seconds = int(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node("executor_bench_subscriber")
taken = [0]
def on_message(data): taken[0] += 1
node.create_subscription(TFMessage, "/tf", on_message, QoSProfile(depth=100), raw=True)
for k in range(subscriptions - 1):
    node.create_subscription(TFMessage, f"/idle_{k}", on_message, QoSProfile(depth=10), raw=True)
executor = common.make_executor()
executor.add_node(node)
print("ready", flush=True)
start = cpu = None
end = time.monotonic() + seconds
while time.monotonic() < end:
    executor.spin_once(timeout_sec=0.1)
    if start is None and taken[0]:
        start, cpu = taken[0], time.process_time()
count = taken[0] - (start or 0)
print(count, (time.process_time() - cpu) / max(count, 1) if cpu is not None else float("nan"))
"""

PUBLISHER = """
import sys, time, rclpy
from rclpy.qos import QoSProfile
from geometry_msgs.msg import TransformStamped
from tf2_msgs.msg import TFMessage
rate, seconds = float(sys.argv[1]), float(sys.argv[2])
rclpy.init()
node = rclpy.create_node("executor_bench_publisher")
publisher = node.create_publisher(TFMessage, "/tf", QoSProfile(depth=100))
message = TFMessage(transforms=[TransformStamped()])
while publisher.get_subscription_count() == 0:
    time.sleep(0.05)
time.sleep(1.0)
burst = 10
start = time.monotonic()
sent = 0
while time.monotonic() - start < seconds:
    for _ in range(burst):
        publisher.publish(message)
    sent += burst
    time.sleep(max(0.0, start + sent / rate - time.monotonic()))
"""


def measure(kind: str, subscriptions: int, rate: float, seconds: float) -> tuple[int, float]:
    """(messages taken, CPU seconds per message) of one subscriber run."""
    subscriber = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, kind, str(subscriptions), str(seconds + 6.0)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert subscriber.stdout is not None
    subscriber.stdout.readline()  # ready
    subprocess.run([sys.executable, "-c", PUBLISHER, str(rate), str(seconds)], check=True)
    out, _ = subscriber.communicate(timeout=seconds + 30.0)
    count, per_message = out.split()
    return int(count), float(per_message)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rate", type=float, default=700.0, help="Hz published")
    parser.add_argument("--seconds", type=float, default=10.0, help="s of publishing per run")
    parser.add_argument("--subscriptions", type=int, nargs="+", default=[1, 40])
    args = parser.parse_args()
    print(f"{'executor':>8} {'subs':>5} {'taken':>7} {'cpu/msg':>9}")
    for subscriptions in args.subscriptions:
        for kind in ("single", "events"):
            start = time.perf_counter()
            count, per_message = measure(kind, subscriptions, args.rate, args.seconds)
            print(
                f"{kind:>8} {subscriptions:5d} {count:7d} {per_message * 1e6:7.0f}us"
                f"   ({time.perf_counter() - start:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
