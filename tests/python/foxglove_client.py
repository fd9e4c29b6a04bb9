"""A Foxglove WebSocket client (the `websockets` package from PyPI),
speaking the protocol as published (subprotocol foxglove.sdk.v1): reads
serverInfo and advertise, subscribes to the topics given, and decodes the
binary messageData frames (opcode 1, u32 subscription id, u64 log time,
payload). Prints one JSON object: {"server": name, "channels": {topic:
{"schemaName", "encoding", "schemaEncoding"}}, "messages": {topic:
[decoded payloads...]}}.

Usage: foxglove_client.py ws://HOST:PORT COUNT TOPIC...
"""

import asyncio
import json
import struct
import sys

import websockets


async def main() -> None:
    url, count, topics = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
    result = {"server": None, "channels": {}, "messages": {t: [] for t in topics}, "times_in_order": True}
    by_subscription = {}
    last_time = {}
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1", ws.subprotocol
        next_id = 1
        while any(len(result["messages"][t]) < count for t in topics):
            frame = await asyncio.wait_for(ws.recv(), timeout=20)
            if isinstance(frame, str):
                message = json.loads(frame)
                if message["op"] == "serverInfo":
                    result["server"] = message["name"]
                elif message["op"] == "advertise":
                    subscriptions = []
                    for channel in message["channels"]:
                        result["channels"][channel["topic"]] = {
                            "schemaName": channel["schemaName"],
                            "encoding": channel["encoding"],
                            "schemaEncoding": channel.get("schemaEncoding"),
                        }
                        if channel["topic"] in topics and channel["topic"] not in by_subscription.values():
                            json.loads(channel["schema"])
                            by_subscription[next_id] = channel["topic"]
                            subscriptions.append({"id": next_id, "channelId": channel["id"]})
                            next_id += 1
                    if subscriptions:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            else:
                opcode = frame[0]
                if opcode != 1:
                    continue
                subscription, log_time = struct.unpack_from("<IQ", frame, 1)
                topic = by_subscription[subscription]
                if log_time < last_time.get(topic, 0):
                    result["times_in_order"] = False
                last_time[topic] = log_time
                if len(result["messages"][topic]) < count:
                    result["messages"][topic].append(json.loads(frame[13:]))
    print(json.dumps(result))


if __name__ == "__main__":
    asyncio.run(main())
