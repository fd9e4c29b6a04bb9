"""Scores a subsume run from its recording with the `mcap` package (PyPI),
independently of the host's scorer, and prints the sub-scores it found as
one JSON object on stdout.

Usage: score_check.py RUN.mcap TASK.json

From the task (docs/lab.md, "Tasks and scores"): the poses of its `pose`
port (COMPONENT.PORT, recorded on /COMPONENT/PORT, each message's
`value` [x, y, heading]) and the commands of its `commands` port
(`value.command`, "VEL v w" or anything else at rest), on the recording's
time line (log time less the channel's `epoch_unix_ns`):

  path_length_m   the sum of the distances between successive poses
  goal_reached    1 if a pose is within the goal's radius, else 0
  time_to_goal_s  the time of the first such pose (only when reached)
  energy          the integral of left^2 + right^2 of the commanded wheel
                  speeds (v -/+ w * wheel_base_m / 2), each command held
                  until the next message on that port, the last until the
                  last message of the recording

and what the scoring component guest-components/rust/scorer-goal-distance
computes from the same streams:

  final_distance_m     from the last pose to the goal's centre
  commands             the commands recorded
  goal_distance_score  final_distance_m + 0.1 * path_length_m
  closest_m            the shortest range reading of the task's `ranges` port
                       (a foxglove.LaserScan) within [range_min, range_max)
"""

import json
import math
import sys

from mcap.reader import make_reader


def topic(port: str) -> str:
    component, _, name = port.partition(".")
    return f"/{component}/{name}"


def wheels(command: str, base: float):
    words = command.split()
    if len(words) >= 3 and words[0] == "VEL":
        try:
            v, w = float(words[1]), float(words[2])
        except ValueError:
            return (0.0, 0.0)
        if math.isfinite(v) and math.isfinite(w):
            return (v - w * base / 2.0, v + w * base / 2.0)
    return (0.0, 0.0)


def main() -> None:
    recording, task_path = sys.argv[1], sys.argv[2]
    with open(task_path) as f:
        task = json.load(f)
    pose_topic = topic(task.get("pose", "motors.pose"))
    cmd_topic = topic(task.get("commands", "envelope.cmd"))
    ranges_topic = topic(task.get("ranges", "motors.ranges"))
    closest = None
    base = task.get("wheel_base_m", 0.3)
    goal = task["goal"]
    poses = []
    commands = []
    last = 0
    with open(recording, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            epoch = int(channel.metadata["epoch_unix_ns"])
            t = message.log_time - epoch
            last = max(last, t)
            if channel.topic == pose_topic:
                value = json.loads(message.data)["value"]
                poses.append((t, value[0], value[1]))
            elif channel.topic == ranges_topic:
                scan = json.loads(message.data)
                for r in scan["ranges"]:
                    if scan["range_min"] <= r < scan["range_max"]:
                        closest = r if closest is None else min(closest, r)
            elif channel.topic == cmd_topic:
                commands.append((t, json.loads(message.data)["value"]["command"]))
    path = 0.0
    for (_, x0, y0), (_, x1, y1) in zip(poses, poses[1:]):
        path += math.hypot(x1 - x0, y1 - y0)
    reached = [t for (t, x, y) in poses if math.hypot(x - goal["x"], y - goal["y"]) <= goal["radius"]]
    energy = 0.0
    for i, (t, command) in enumerate(commands):
        until = commands[i + 1][0] if i + 1 < len(commands) else last
        left, right = wheels(command, base)
        energy += (left * left + right * right) * ((until - t) / 1e9)
    found = {"path_length_m": path, "goal_reached": 1.0 if reached else 0.0, "energy": energy, "poses": len(poses)}
    if poses:
        _, x, y = poses[-1]
        final = math.hypot(x - goal["x"], y - goal["y"])
        found["final_distance_m"] = final
        found["goal_distance_score"] = final + 0.1 * path
    found["commands"] = len(commands)
    if closest is not None:
        found["closest_m"] = closest
    if reached:
        found["time_to_goal_s"] = reached[0] / 1e9
    print(json.dumps(found))


if __name__ == "__main__":
    main()
