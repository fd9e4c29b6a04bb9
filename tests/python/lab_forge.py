"""Sends a subsume robot lab messages straight to its queryables, signed
with whatever secret a case names, through the eclipse-zenoh package
(tests/all/labnet.rs drives it): a forger on the lab's Zenoh network.

    lab_forge.py ENDPOINT LAB ROBOT CASES_JSON

Opens a client session to ENDPOINT, and for each case of the JSON list
CASES_JSON ({"op": "dispatch" | "estop", "secret": TEXT, "skew_ms": N,
"duration_s": S, "config_text": XML}) builds the message as docs/lab.md
describes it (an SLB1 envelope: HMAC-SHA256 over the lab's name, the kind,
the header's length and the header; the header names ROBOT, the time, and
a fresh nonce), sends it as the payload of a query on
subsume/lab/LAB/rpc/ROBOT/OP, and prints one JSON object per case: the
case's op and the robot's answers (the header of a signed one, or the text
of an unsigned refusal).

The envelope is written here from the format alone, not with subsume's
code: a robot that refuses these refuses any peer, not only subsume's own.
"""

import hashlib
import hmac
import json
import os
import struct
import sys
import time

from lab_tokens import client

MAGIC = b"SLB1"
KINDS = {"dispatch": 4, "dispatch-reply": 5, "estop": 7, "ack": 8}


def seal(lab, secret, kind, header):
    """The envelope of `header` (bytes) of `kind`, signed with `secret`."""
    signed = lab.encode() + bytes([0, kind, 0]) + struct.pack("<I", len(header)) + header
    tag = hmac.new(secret.encode(), signed, hashlib.sha256).digest()
    return MAGIC + tag + bytes([kind]) + struct.pack("<I", len(header)) + header


def header_of(envelope):
    """The JSON header of an envelope (not checked: only read)."""
    if envelope[:4] != MAGIC or len(envelope) < 41:
        return {"not_an_envelope": envelope[:64].hex()}
    length = struct.unpack("<I", envelope[37:41])[0]
    return json.loads(envelope[41 : 41 + length])


def message(case, robot, lab_id):
    issued = int(time.time() * 1000) + case.get("skew_ms", 0)
    to = {"robot": robot, "issued_unix_ms": issued, "nonce": os.urandom(16).hex()}
    if case["op"] == "estop":
        return {"v": 2, "to": to, "by": "mallory"}
    return {
        "v": 2,
        "to": to,
        "lab_id": lab_id,
        "submitter": "mallory",
        "role": "admin",
        "platforms": ["control", "network"],
        "label": "forged",
        "duration_s": case.get("duration_s", 5.0),
        "set": {
            "config_name": "forged.xml",
            "config_text": case["config_text"],
            "platform": "control",
            "sources": {},
        },
    }


def main():
    endpoint, lab, robot, cases = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4])
    session = client(endpoint)
    try:
        for n, case in enumerate(cases):
            header = json.dumps(message(case, robot, 9000 + n)).encode()
            payload = seal(lab, case["secret"], KINDS[case["op"]], header)
            answers = []
            key = f"subsume/lab/{lab}/rpc/{robot}/{case['op']}"
            for reply in session.get(key, payload=payload, timeout=60.0):
                if reply.ok is not None:
                    answers.append(header_of(bytes(reply.ok.payload.to_bytes())))
                else:
                    answers.append({"refused": bytes(reply.err.payload.to_bytes()).decode("utf-8", "replace")})
            print(json.dumps({"op": case["op"], "answers": answers}), flush=True)
    finally:
        session.close()


if __name__ == "__main__":
    main()
