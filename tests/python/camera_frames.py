"""Reads the camera's pictures out of a subsume recording with the `mcap`
package (PyPI) and decodes each JPEG with Pillow (PyPI): decoders no one
here wrote. Prints one JSON object on stdout:

    {"frames": [{"log_time": ns, "stamp_ns": ns, "format": "jpeg", "width": w,
                 "height": h, "mode": "RGB", "robot_px": [x, y] | null,
                 "luma": mean of Pillow's ITU-R 601-2 luma}],
     "poses": [[log_time, x, y, heading], ...]}

robot_px is the centre of the pixels of the robot's colour (blue, within a
JPEG's error), or null when there are none.

Usage: camera_frames.py FILE.mcap IMAGE_TOPIC POSE_TOPIC
"""

import base64
import io
import json
import sys

from mcap.reader import make_reader
from PIL import Image, ImageStat

# The robot's colour (host/src/camera/render.rs ROBOT) and how far a JPEG
# pixel may stray from it.
ROBOT = (30, 90, 220)
TOLERANCE = 45


def robot_centre(image):
    rgb = image.convert("RGB")
    width, height = rgb.size
    pixels = rgb.load()
    xs, ys, n = 0.0, 0.0, 0
    for y in range(height):
        for x in range(width):
            r, g, b = pixels[x, y]
            if abs(r - ROBOT[0]) < TOLERANCE and abs(g - ROBOT[1]) < TOLERANCE and abs(b - ROBOT[2]) < TOLERANCE:
                xs += x + 0.5
                ys += y + 0.5
                n += 1
    return [xs / n, ys / n] if n else None


def main() -> None:
    path, image_topic, pose_topic = sys.argv[1:4]
    frames, poses = [], []
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(topics=[image_topic, pose_topic]):
            body = json.loads(message.data)
            if channel.topic == pose_topic:
                poses.append([message.log_time] + body["value"])
                continue
            assert schema.name == "foxglove.CompressedImage", schema.name
            image = Image.open(io.BytesIO(base64.b64decode(body["data"])))
            image.load()
            stamp = body["timestamp"]
            frames.append(
                {
                    "log_time": message.log_time,
                    "stamp_ns": stamp["sec"] * 1_000_000_000 + stamp["nsec"],
                    "format": body["format"],
                    "decoded_format": image.format,
                    "width": image.size[0],
                    "height": image.size[1],
                    "mode": image.mode,
                    "robot_px": robot_centre(image),
                    "luma": ImageStat.Stat(image.convert("L")).mean[0],
                }
            )
    json.dump({"frames": frames, "poses": poses}, sys.stdout)


if __name__ == "__main__":
    main()
