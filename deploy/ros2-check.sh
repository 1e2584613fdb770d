#!/usr/bin/env bash
# The live check of kmead's ROS 2 output against a real rmw_zenoh (docs/ros2.md).
#
#   deploy/ros2-check.sh [jazzy|kilted]      # default jazzy
#
# Needs docker and this repository's .venv with the zenoh extra (pip install -e '.[zenoh]').
# A ros:<distro> container (host network) installs rmw_zenoh, starts its router (rmw_zenohd,
# tcp/[::]:7447) and an rclpy subscriber on /kmea/amr1/pose and /tf; kmead runs here on the
# simulated floor and connects to that router. The subscriber prints what it received and
# exits 0 only if both topics delivered messages with frame map and a non-zero covariance;
# `ros2 topic list -t` and `ros2 node list` are printed too.
# Written for the change that added the ROS 2 output; NOT run on the machine it was written
# on (no docker there).
set -euo pipefail
distro="${1:-jazzy}"
here="$(cd "$(dirname "$0")/.." && pwd)"
py="${PYTHON:-$here/.venv/bin/python}"
command -v docker >/dev/null || { echo "ros2-check: docker is needed" >&2; exit 2; }
"$py" -c 'import zenoh, rosbags' 2>/dev/null \
    || { echo "ros2-check: $py lacks the zenoh extra: pip install -e '.[zenoh]'" >&2; exit 2; }

name="kmea-ros2-check-$$"
cleanup() { docker rm -f "$name" >/dev/null 2>&1 || true; }
trap cleanup EXIT

subscriber=$(cat <<'PY'
import sys, rclpy
from rclpy.node import Node
from geometry_msgs.msg import PoseWithCovarianceStamped
from tf2_msgs.msg import TFMessage

class Check(Node):
    def __init__(self):
        super().__init__("kmea_check")
        self.poses, self.tfs, self.bad = [], [], []
        self.create_subscription(PoseWithCovarianceStamped, "/kmea/amr1/pose", self.pose, 10)
        self.create_subscription(TFMessage, "/tf", self.tf, 100)
    def pose(self, m):
        self.poses.append(m)
        if m.header.frame_id != "map" or not any(m.pose.covariance):
            self.bad.append(m)
    def tf(self, m):
        self.tfs.extend(t for t in m.transforms if t.child_frame_id.endswith("/kmea"))

rclpy.init()
n = Check()
end = n.get_clock().now().nanoseconds + 40e9
while rclpy.ok() and n.get_clock().now().nanoseconds < end and len(n.poses) < 60:
    rclpy.spin_once(n, timeout_sec=0.5)
print(f"received {len(n.poses)} poses, {len(n.tfs)} transforms, {len(n.bad)} bad")
if n.poses:
    m = n.poses[-1]
    print("last pose:", m.header, m.pose.pose, list(m.pose.covariance)[:2], "...")
sys.exit(0 if n.poses and n.tfs and not n.bad else 1)
PY
)

echo "ros2-check: starting ros:$distro with rmw_zenoh (first run downloads packages)"
docker run -d --rm --name "$name" --network host "ros:$distro" sleep 600 >/dev/null
docker exec "$name" bash -c "apt-get update -qq && apt-get install -y -qq ros-$distro-rmw-zenoh-cpp >/dev/null"
docker exec -d "$name" bash -c "source /opt/ros/$distro/setup.bash && ros2 run rmw_zenoh_cpp rmw_zenohd"
sleep 3
printf '%s\n' "$subscriber" | docker exec -i "$name" bash -c 'cat > /tmp/check.py'
docker exec -d -e RMW_IMPLEMENTATION=rmw_zenoh_cpp "$name" bash -c \
    "source /opt/ros/$distro/setup.bash && python3 /tmp/check.py > /tmp/check.out 2>&1; echo \$? > /tmp/check.rc"
sleep 3

echo "ros2-check: kmead on the simulated floor, connected to tcp/127.0.0.1:7447"
(cd "$here" && "$py" -m kmead.cli --headless --free-ports --frames 900 --status-every 0 \
    --set zenoh.enabled=true --set 'zenoh.connect=["tcp/127.0.0.1:7447"]') &
kmead=$!
sleep 10
docker exec -e RMW_IMPLEMENTATION=rmw_zenoh_cpp "$name" bash -c \
    "source /opt/ros/$distro/setup.bash && ros2 node list && ros2 topic list -t && ros2 topic info -v /kmea/amr1/pose"
for _ in $(seq 60); do
    docker exec "$name" test -f /tmp/check.rc && break
    sleep 1
done
kill -INT "$kmead" 2>/dev/null || true
wait "$kmead" || true
docker exec "$name" cat /tmp/check.out
rc=$(docker exec "$name" cat /tmp/check.rc 2>/dev/null || echo 1)
[ "$rc" = 0 ] && echo "ros2-check: OK ($distro)" || echo "ros2-check: FAILED ($distro)"
exit "$rc"
