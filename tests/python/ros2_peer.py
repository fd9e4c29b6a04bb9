"""A ROS 2 peer for the ROS 2 face, built on implementations no one here
wrote: the `eclipse-zenoh` package is the Zenoh peer, `rosbags` serializes
and deserializes every message (CDR) and computes the REP-2016 type hashes
from the message definitions.

Usage: ros2_peer.py MODE ENDPOINT
  MODE robot: play ROS 2 tools watching and commanding subsume (use A):
    listen on ENDPOINT; publish a Twist on /cmd_vel 20 times a second;
    decode /odom and /scan; list the liveliness tokens.
  MODE base: play a ROS 2 robot base (use B): listen on ENDPOINT; publish
    /scan and /odom 20 times a second; decode every /cmd_vel.
  MODE hashes: print rosbags' RIHS01 hashes of the supported types.

The peer prints "ready" once its session is up, runs until stdin closes,
then prints one JSON summary line. Wire format (key expressions, the
attachment, liveliness tokens) as in ros2/rmw_zenoh docs/design.md.
"""

import json
import struct
import sys
import threading
import time

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
TYPES = [
    "geometry_msgs/msg/Twist",
    "nav_msgs/msg/Odometry",
    "sensor_msgs/msg/LaserScan",
    "rcl_interfaces/msg/Log",
    "std_msgs/msg/Bool",
]


def dds(name):
    pkg, kind, msg = name.split("/")
    return f"{pkg}::{kind}::dds_::{msg}_"


def key(topic, name, domain=0):
    return f"{domain}/{topic}/{dds(name)}/{TS.hash_rihs01(name)}"


def attachment(seq, gid):
    # 8 bytes sequence number, 8 bytes timestamp (ns), 1 byte GID length, GID.
    return struct.pack("<qqB", seq, time.time_ns(), 16) + gid


def check_attachment(att, last_seq):
    """The attachment's sequence number, after checking its layout."""
    raw = bytes(att.to_bytes()) if att is not None else b""
    assert len(raw) == 33 and raw[16] == 16, f"attachment {raw!r}"
    seq, stamp = struct.unpack("<qq", raw[:16])
    assert seq > last_seq, (seq, last_seq)
    assert abs(stamp - time.time_ns()) < 60e9, stamp
    return seq


def open_session(endpoint):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def msg(type_name, /, **fields):
    return TS.types[type_name](**fields)


def header(frame):
    now = time.time_ns()
    return msg(
        "std_msgs/msg/Header",
        stamp=msg("builtin_interfaces/msg/Time", sec=now // 10**9, nanosec=now % 10**9),
        frame_id=frame,
    )


def twist(v, w):
    vec = lambda x, y, z: msg("geometry_msgs/msg/Vector3", x=x, y=y, z=z)
    return msg("geometry_msgs/msg/Twist", linear=vec(v, 0.0, 0.0), angular=vec(0.0, 0.0, w))


def serialize(m, name):
    return bytes(TS.serialize_cdr(m, name))


def wait_for_stdin_close():
    done = threading.Event()

    def reader():
        sys.stdin.read()
        done.set()

    threading.Thread(target=reader, daemon=True).start()
    return done


def robot(endpoint, estop_at=None):
    """Drives with Twists on /cmd_vel; with `estop_at` (s), publishes
    std_msgs/Bool true on /estop then, and keeps sending Twists."""
    session = open_session(endpoint)
    lock = threading.Lock()
    state = {"odom": [], "odom_t": [], "scans": 0, "scan": None, "bad": [], "seq": {"odom": 0, "scan": 0}}

    def on(topic, name):
        def callback(sample):
            try:
                with lock:
                    state["seq"][topic] = check_attachment(sample.attachment, state["seq"][topic])
                    m = TS.deserialize_cdr(bytes(sample.payload.to_bytes()), name)
                    if topic == "odom":
                        p = m.pose.pose
                        yaw = 2.0 * np.arctan2(p.orientation.z, p.orientation.w)
                        state["odom"].append([p.position.x, p.position.y, float(yaw), m.header.frame_id, m.child_frame_id])
                        state["odom_t"].append(time.monotonic())
                    else:
                        state["scans"] += 1
                        state["scan"] = {
                            "angle_min": float(m.angle_min),
                            "angle_max": float(m.angle_max),
                            "angle_increment": float(m.angle_increment),
                            "range_max": float(m.range_max),
                            "ranges": [float(r) for r in m.ranges],
                            "frame_id": m.header.frame_id,
                        }
            except Exception as e:  # noqa: BLE001 - every failure is reported to the test
                state["bad"].append(f"{topic}: {e!r}")

        return callback

    subs = [
        session.declare_subscriber(key("odom", "nav_msgs/msg/Odometry"), on("odom", "nav_msgs/msg/Odometry")),
        session.declare_subscriber(key("scan", "sensor_msgs/msg/LaserScan"), on("scan", "sensor_msgs/msg/LaserScan")),
    ]
    pub = session.declare_publisher(key("cmd_vel", "geometry_msgs/msg/Twist"))
    estop_pub = session.declare_publisher(key("estop", "std_msgs/msg/Bool"))
    odom_at_estop = None
    gid = bytes(range(16))
    print("ready", flush=True)
    done = wait_for_stdin_close()
    seq = 0
    garbage = 0
    while not done.wait(0.05):
        seq += 1
        pub.put(serialize(twist(0.3, 0.0), "geometry_msgs/msg/Twist"), attachment=attachment(seq, gid))
        if estop_at is not None and odom_at_estop is None and seq * 0.05 >= estop_at:
            estop_pub.put(serialize(msg("std_msgs/msg/Bool", data=True), "std_msgs/msg/Bool"), attachment=attachment(seq, gid))
            with lock:
                odom_at_estop = state["odom"][-1] if state["odom"] else None
            estop_t = time.monotonic()
        if seq % 10 == 0:
            # Untrusted input: a Twist cut short, which the host must count and drop.
            garbage += 1
            pub.put(serialize(twist(9.0, 9.0), "geometry_msgs/msg/Twist")[:20], attachment=attachment(seq, gid))
    tokens = sorted(str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**") if r.ok is not None)
    with lock:
        summary = {
            "odom_count": len(state["odom"]),
            "odom_first": state["odom"][0] if state["odom"] else None,
            "odom_last": state["odom"][-1] if state["odom"] else None,
            "scans": state["scans"],
            "scan": state["scan"],
            "bad": state["bad"],
            "tokens": tokens,
            "sent": seq,
            "garbage": garbage,
            "odom_at_estop": odom_at_estop,
            # The odometry from one second after the e-stop on.
            "odom_after_estop": [o for o, t in zip(state["odom"], state["odom_t"]) if odom_at_estop is not None and t >= estop_t + 1.0],
        }
    del subs
    session.close()
    print(json.dumps(summary), flush=True)


def base(endpoint):
    session = open_session(endpoint)
    lock = threading.Lock()
    state = {"twists": [], "bad": [], "seq": 0}

    def on_cmd(sample):
        try:
            with lock:
                state["seq"] = check_attachment(sample.attachment, state["seq"])
                m = TS.deserialize_cdr(bytes(sample.payload.to_bytes()), "geometry_msgs/msg/Twist")
                state["twists"].append([m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z])
        except Exception as e:  # noqa: BLE001
            state["bad"].append(repr(e))

    sub = session.declare_subscriber(key("cmd_vel", "geometry_msgs/msg/Twist"), on_cmd)
    scan_pub = session.declare_publisher(key("scan", "sensor_msgs/msg/LaserScan"))
    odom_pub = session.declare_publisher(key("odom", "nav_msgs/msg/Odometry"))
    gid = bytes(range(16, 32))
    print("ready", flush=True)
    done = wait_for_stdin_close()
    seq = 0
    zeros = np.zeros(36, dtype=np.float64)
    while not done.wait(0.05):
        seq += 1
        scan = msg(
            "sensor_msgs/msg/LaserScan",
            header=header("base_scan"),
            angle_min=-1.5708,
            angle_max=1.5708,
            angle_increment=3.14159 / 8,
            time_increment=0.0,
            scan_time=0.05,
            range_min=0.05,
            range_max=4.0,
            ranges=np.array([3.0] * 4 + [float("inf")] + [3.0] * 4, dtype=np.float32),
            intensities=np.array([], dtype=np.float32),
        )
        scan_pub.put(serialize(scan, "sensor_msgs/msg/LaserScan"), attachment=attachment(seq, gid))
        pose = msg(
            "geometry_msgs/msg/PoseWithCovariance",
            pose=msg(
                "geometry_msgs/msg/Pose",
                position=msg("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                orientation=msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            covariance=zeros,
        )
        odom = msg(
            "nav_msgs/msg/Odometry",
            header=header("odom"),
            child_frame_id="base_link",
            pose=pose,
            twist=msg("geometry_msgs/msg/TwistWithCovariance", twist=twist(0.0, 0.0), covariance=zeros),
        )
        odom_pub.put(serialize(odom, "nav_msgs/msg/Odometry"), attachment=attachment(seq, gid))
    with lock:
        summary = {"twists": state["twists"], "bad": state["bad"], "sent": seq}
    del sub
    session.close()
    print(json.dumps(summary), flush=True)


def fixtures():
    """rosbags' bytes for fixed messages, which the host's encoders must match."""
    stamp = msg("builtin_interfaces/msg/Time", sec=12, nanosec=34)
    hdr = lambda frame: msg("std_msgs/msg/Header", stamp=stamp, frame_id=frame)
    zeros = np.zeros(36, dtype=np.float64)
    out = {
        "twist": serialize(twist(0.5, -1.0), "geometry_msgs/msg/Twist"),
        "bool": serialize(msg("std_msgs/msg/Bool", data=True), "std_msgs/msg/Bool"),
        "log": serialize(
            msg("rcl_interfaces/msg/Log", stamp=stamp, level=20, name="subsume", msg="hello", file="", function="", line=0),
            "rcl_interfaces/msg/Log",
        ),
        "scan": serialize(
            msg(
                "sensor_msgs/msg/LaserScan",
                header=hdr("base_scan"),
                angle_min=-1.5,
                angle_max=1.5,
                angle_increment=1.5,
                time_increment=0.0,
                scan_time=0.0,
                range_min=0.0,
                range_max=4.0,
                ranges=np.array([1.0, 2.0, 3.0], dtype=np.float32),
                intensities=np.array([], dtype=np.float32),
            ),
            "sensor_msgs/msg/LaserScan",
        ),
        "odom": serialize(
            msg(
                "nav_msgs/msg/Odometry",
                header=hdr("odom"),
                child_frame_id="base_link",
                pose=msg(
                    "geometry_msgs/msg/PoseWithCovariance",
                    pose=msg(
                        "geometry_msgs/msg/Pose",
                        position=msg("geometry_msgs/msg/Point", x=1.5, y=-2.0, z=0.0),
                        orientation=msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.5, w=0.75),
                    ),
                    covariance=zeros,
                ),
                twist=msg("geometry_msgs/msg/TwistWithCovariance", twist=twist(0.0, 0.0), covariance=zeros),
            ),
            "nav_msgs/msg/Odometry",
        ),
    }
    print(json.dumps({k: v.hex() for k, v in out.items()}))


def main():
    mode = sys.argv[1]
    if mode == "hashes":
        print(json.dumps({t: TS.hash_rihs01(t) for t in TYPES}))
    elif mode == "fixtures":
        fixtures()
    elif mode == "robot":
        robot(sys.argv[2])
    elif mode == "robot-estop":
        robot(sys.argv[2], estop_at=float(sys.argv[3]))
    elif mode == "base":
        base(sys.argv[2])
    else:
        sys.exit(f"unknown mode {mode}")


if __name__ == "__main__":
    main()
