"""Reads the world out of a subsume recording with the `mcap` package
(PyPI) and compares it with the world file, read here on its own: every
wall, box side and side of the bounds must be one cube of the
`foxglove.SceneUpdate` on /world/scene, centred on it, as long as it and
turned along it; every circle one cylinder; the goal a line loop around it.
Prints one JSON object: {"messages": N, "schema": name, "encoding": ...,
"message_encoding": ..., "cubes": N, "cylinders": N, "segments": N,
"circles": N, "problems": [...]}.

Usage: camera_scene.py FILE.mcap FILE.world
"""

import json
import math
import sys

from mcap.reader import make_reader

CLOSE = 1e-6


def world_shapes(path):
    segments, circles, goal = [], [], None
    for line in open(path):
        words = line.split("#")[0].split()
        if not words:
            continue
        keyword, numbers = words[0], [float(w) for w in words[1:]]
        if keyword == "bounds":
            x0, y0, x1, y1 = numbers
            segments += [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
        elif keyword == "box":
            x0, y0, x1, y1 = numbers
            segments += [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
        elif keyword == "wall":
            segments.append(((numbers[0], numbers[1]), (numbers[2], numbers[3])))
        elif keyword == "circle":
            circles.append(tuple(numbers))
        elif keyword == "goal":
            goal = tuple(numbers)
    return segments, circles, goal


def yaw(orientation):
    return 2 * math.atan2(orientation["z"], orientation["w"])


def same_angle_mod_pi(a, b):
    d = (a - b) % math.pi
    return min(d, math.pi - d) < 1e-6


def main() -> None:
    recording, world = sys.argv[1:3]
    segments, circles, goal = world_shapes(world)
    out = {"messages": 0, "problems": []}
    scene = None
    with open(recording, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=["/world/scene"]):
            out["messages"] += 1
            out["schema"], out["encoding"], out["message_encoding"] = schema.name, schema.encoding, channel.message_encoding
            scene = json.loads(message.data)
    if scene is None:
        print(json.dumps(out))
        return
    cubes = [c for e in scene["entities"] for c in e["cubes"]]
    cylinders = [c for e in scene["entities"] for c in e["cylinders"]]
    lines = [l for e in scene["entities"] for l in e["lines"]]
    out.update(cubes=len(cubes), cylinders=len(cylinders), segments=len(segments), circles=len(circles))
    unmatched = list(cubes)
    for (ax, ay), (bx, by) in segments:
        cx, cy, length = (ax + bx) / 2, (ay + by) / 2, math.hypot(bx - ax, by - ay)
        angle = math.atan2(by - ay, bx - ax)
        match = next(
            (
                c
                for c in unmatched
                if abs(c["pose"]["position"]["x"] - cx) < CLOSE
                and abs(c["pose"]["position"]["y"] - cy) < CLOSE
                and abs(c["size"]["x"] - length) < CLOSE
                and same_angle_mod_pi(yaw(c["pose"]["orientation"]), angle)
            ),
            None,
        )
        if match is None:
            out["problems"].append(f"no cube for the segment {(ax, ay)} - {(bx, by)}")
        else:
            unmatched.remove(match)
    for x, y, r in circles:
        if not any(
            abs(c["pose"]["position"]["x"] - x) < CLOSE
            and abs(c["pose"]["position"]["y"] - y) < CLOSE
            and abs(c["size"]["x"] - 2 * r) < CLOSE
            for c in cylinders
        ):
            out["problems"].append(f"no cylinder for the circle {(x, y, r)}")
    if unmatched:
        out["problems"].append(f"{len(unmatched)} cubes match no segment of the world")
    gx, gy, gr = goal
    rings = [l for l in lines if l["type"] == 1]
    if not rings or any(abs(math.hypot(p["x"] - gx, p["y"] - gy) - gr) > CLOSE for p in rings[0]["points"]):
        out["problems"].append("no line loop around the goal")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
