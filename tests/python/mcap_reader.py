"""Reads a subsume recording with the `mcap` package (PyPI), a reader no one
here wrote, and prints what it found as one JSON object on stdout:

    {"complete": bool, "channels": {topic: {"schema": name, "schema_encoding": ...,
     "message_encoding": ..., "count": n}}, "in_order_per_channel": bool,
     "out_of_order": [{"topic": ..., "message": n, "log_time": t, "after": t}],
     "messages": n, "summary": {...} | null, "first": {topic: message}, "last": {...}}

"out_of_order" names the first few messages whose log time is earlier than
the one before it on the same channel (n counts the file's messages from 0).

Usage: mcap_reader.py FILE.mcap [--truncated] [--values TOPIC]...

--truncated reads a file a killed host left (no summary, no footer): the
chunks are read in order with the non-seeking reader until the data stops,
each chunk's CRC checked.

--values TOPIC also prints every decoded message of TOPIC, in file order,
under "values": {topic: [message, ...]}.
"""

import json
import sys

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader


def main() -> None:
    path = sys.argv[1]
    truncated = "--truncated" in sys.argv[2:]
    wanted = {sys.argv[i + 1] for i, a in enumerate(sys.argv[:-1]) if a == "--values"}
    values = {topic: [] for topic in wanted}
    channels = {}
    last_time = {}
    in_order = True
    out_of_order = []
    messages = 0
    first = {}
    last = {}
    complete = True
    summary = None
    with open(path, "rb") as f:
        if truncated:
            reader = NonSeekingReader(f, validate_crcs=True)
        else:
            reader = make_reader(f, validate_crcs=True)
            s = reader.get_summary()
            if s is not None and s.statistics is not None:
                summary = {
                    "message_count": s.statistics.message_count,
                    "channel_count": s.statistics.channel_count,
                    "chunk_count": s.statistics.chunk_count,
                    "channel_message_counts": {
                        s.channels[c].topic: n for c, n in s.statistics.channel_message_counts.items()
                    },
                }
        try:
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                entry = channels.setdefault(
                    channel.topic,
                    {
                        "schema": schema.name if schema else None,
                        "schema_encoding": schema.encoding if schema else None,
                        "message_encoding": channel.message_encoding,
                        "count": 0,
                        "schema_is_json": False,
                    },
                )
                if schema is not None and not entry["schema_is_json"]:
                    json.loads(schema.data)
                    entry["schema_is_json"] = True
                entry["count"] += 1
                decoded = json.loads(message.data)
                if channel.topic not in first:
                    first[channel.topic] = decoded
                last[channel.topic] = decoded
                if channel.topic in values:
                    values[channel.topic].append(decoded)
                if message.log_time < last_time.get(channel.topic, 0):
                    in_order = False
                    if len(out_of_order) < 5:
                        out_of_order.append(
                            {
                                "topic": channel.topic,
                                "message": messages,
                                "log_time": message.log_time,
                                "after": last_time[channel.topic],
                            }
                        )
                last_time[channel.topic] = message.log_time
                messages += 1
        except (McapError, EOFError, ValueError) as e:
            if not truncated:
                raise
            complete = False
            print(f"stopped at the cut: {type(e).__name__}: {e}", file=sys.stderr)
    print(
        json.dumps(
            {
                "complete": complete,
                "channels": channels,
                "in_order_per_channel": in_order,
                "out_of_order": out_of_order,
                "messages": messages,
                "summary": summary,
                "first": first,
                "last": last,
                "values": values,
            }
        )
    )


if __name__ == "__main__":
    main()
