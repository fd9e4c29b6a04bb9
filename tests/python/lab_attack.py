"""A peer on a subsume lab's Zenoh network that holds no lab secret, through
the eclipse-zenoh package (tests/all/labnet.rs drives it; docs/lab.md,
"What holds against a peer without the secret"). Each attack is a
subcommand:

    lab_attack.py rogue ENDPOINT LAB ROBOT CAPTURED_SECRET [USER PASSWORD]
        Declares complete queryables on every rpc key of ROBOT and answers
        each query, at once, with garbage, an unsigned refusal, a reply
        carrying the query's own nonce but signed with a made-up secret,
        and signed replies of the right kind bound to other requests (the
        replies a peer could have captured from earlier exchanges; the test
        gives it the lab's secret only to stand for them: they never carry
        the nonce of a query they answer). Prints "ready", runs until its
        standard input closes, then prints the queries it answered by op.
        With USER and PASSWORD it logs in to a router as that user (a
        third user of a router with access control, such as
        config/zenoh-lab-router.json5); a session the router refuses is
        printed as {"refused": WHY}.

    lab_attack.py capture ENDPOINT LAB ROBOT OTHER_ROBOT
        Declares a (not complete) queryable on ROBOT's dispatch key, takes
        the first dispatch the lab sends (no answer), then replays it twice
        to ROBOT and once to OTHER_ROBOT, and prints what each answered.

    lab_attack.py flood ENDPOINT LAB ROBOT SECONDS RATE
        Sends RATE junk queries a second for SECONDS to ROBOT's rpc keys
        (half of them its emergency stop's): random bytes in an SLB1
        envelope with a random MAC. Prints "ready" when it starts and how
        many it sent when it is done.

    lab_attack.py oversized ENDPOINT LAB ROBOT COUNT BYTES
        Sends COUNT messages of BYTES each (far over the lab's bound, which
        Zenoh itself applies to what it reassembles) to ROBOT's rpc keys,
        as queries and as puts, a fifth of a second apart. Prints "ready",
        then how many it sent and how many sends failed (Zenoh may close
        the link of a peer that sends more than its bound).

    lab_attack.py token ENDPOINT LAB ROBOT
        Reads ROBOT's liveliness tokens and declares each again from this
        session, so they stay when the robot's go. Prints "ready" with the
        keys, runs until its standard input closes.

The envelope is written here from the format alone (docs/lab.md), not
with subsume's code.
"""

import json
import os
import struct
import sys
import threading
import time

import zenoh
from lab_forge import MAGIC, seal
from lab_tokens import client

OPS = ["dispatch", "stop", "estop", "results", "file", "baseline", "live"]
# Kinds of the replies each op's asker takes.
DISPATCH_REPLY, ACK, RESULTS, CHUNK, BASELINE, LIVE = 5, 8, 10, 12, 14, 16


def header_of(envelope):
    if envelope[:4] != MAGIC or len(envelope) < 41:
        return None
    length = struct.unpack("<I", envelope[37:41])[0]
    try:
        return json.loads(envelope[41 : 41 + length])
    except ValueError:
        return None


def answers_of(replies):
    """Each reply: the header of a signed one, or an unsigned refusal's text."""
    out = []
    for reply in replies:
        if reply.ok is not None:
            payload = bytes(reply.ok.payload.to_bytes())
            out.append({"header": header_of(payload)})
        else:
            out.append({"refused": bytes(reply.err.payload.to_bytes()).decode("utf-8", "replace")})
    return out


def captured_reply(op, robot, request):
    """A reply of `op`'s kind bound to another request than `request`."""
    re = {"robot": robot, "nonce": os.urandom(16).hex()}
    lab_id = (request or {}).get("lab_id", 1)
    if op == "dispatch":
        body = {"lab_id": lab_id, "outcome": "refused", "reasons": ["rogue: captured"]}
        return DISPATCH_REPLY, body | {"v": 2, "re": re}
    if op == "results":
        body = {"lab_id": lab_id, "found": False, "state": None, "history": [], "reasons": [], "run": None, "files": []}
        return RESULTS, body | {"v": 2, "re": re}
    if op == "file":
        return CHUNK, {"v": 2, "re": re, "offset": 0, "total": 0, "missing": "rogue: captured"}
    return ACK, {"v": 2, "re": re, "ok": False, "message": "rogue: captured"}


def rogue(endpoint, lab, robot, captured_secret, user=None, password=None):
    try:
        session = client(endpoint, user, password)
    except zenoh.ZError as why:
        print(json.dumps({"refused": str(why)}), flush=True)
        return
    answered = {op: 0 for op in OPS}
    lock = threading.Lock()

    def answer(op):
        def on_query(query):
            payload = bytes(query.payload.to_bytes()) if query.payload is not None else b""
            request = header_of(payload)
            key = query.key_expr
            query.reply(key, b"garbage, not a lab message")
            query.reply(key, MAGIC + os.urandom(60))
            # The query's own nonce and robot, signed with a made-up secret.
            if request and "to" in request:
                kind, body = captured_reply(op, robot, request)
                body["re"] = {"robot": robot, "nonce": request["to"]["nonce"]}
                query.reply(key, seal(lab, "made-up-secret-0123456789", kind, json.dumps(body).encode()))
            # Signed replies captured from other exchanges: another nonce,
            # and another robot.
            kind, body = captured_reply(op, robot, request)
            query.reply(key, seal(lab, captured_secret, kind, json.dumps(body).encode()))
            body["re"]["robot"] = "someone-else"
            query.reply(key, seal(lab, captured_secret, kind, json.dumps(body).encode()))
            query.reply_err(b"refused: rogue")
            with lock:
                answered[op] += 1

        return on_query

    queryables = [
        session.declare_queryable(f"subsume/lab/{lab}/rpc/{robot}/{op}", answer(op), complete=True) for op in OPS
    ]
    print("ready", flush=True)
    sys.stdin.read()
    with lock:
        print(json.dumps({"answered": answered}), flush=True)
    for queryable in queryables:
        queryable.undeclare()
    session.close()


def capture(endpoint, lab, robot, other):
    session = client(endpoint)
    captured = []
    got = threading.Event()

    def on_query(query):
        if not captured and query.payload is not None:
            captured.append(bytes(query.payload.to_bytes()))
            got.set()

    queryable = session.declare_queryable(f"subsume/lab/{lab}/rpc/{robot}/dispatch", on_query)
    print("ready", flush=True)
    if not got.wait(300):
        print(json.dumps({"error": "no dispatch came"}), flush=True)
        return
    queryable.undeclare()
    # Let the robot take the real one first.
    time.sleep(1.0)
    replays = []
    for target in [robot, robot, other]:
        key = f"subsume/lab/{lab}/rpc/{target}/dispatch"
        answers = answers_of(session.get(key, payload=captured[0], timeout=30.0))
        replays.append({"to": target, "answers": answers})
    print(json.dumps({"captured": header_of(captured[0]), "replays": replays}), flush=True)
    session.close()


def flood(endpoint, lab, robot, seconds, rate):
    session = client(endpoint)
    keys = [f"subsume/lab/{lab}/rpc/{robot}/{op}" for op in OPS]
    sent = 0
    start = time.monotonic()
    print("ready", flush=True)
    while time.monotonic() - start < seconds:
        due = int((time.monotonic() - start) * rate)
        while sent < due:
            # Half at the emergency stop, the rest over every key.
            key = keys[2] if sent % 2 == 0 else keys[sent % len(keys)]
            junk = MAGIC + os.urandom(32) + bytes([7]) + struct.pack("<I", 40) + os.urandom(40)
            session.get(key, lambda reply: None, payload=junk, timeout=5.0)
            sent += 1
        time.sleep(0.002)
    elapsed = time.monotonic() - start
    print(json.dumps({"sent": sent, "seconds": elapsed}), flush=True)
    time.sleep(0.5)
    session.close()


def oversized(endpoint, lab, robot, count, size):
    session = client(endpoint)
    keys = [f"subsume/lab/{lab}/rpc/{robot}/{op}" for op in OPS]
    # An envelope whose header claims the whole size: a reader that trusted
    # it would hold every byte.
    payload = MAGIC + os.urandom(32) + bytes([7]) + struct.pack("<I", size) + bytes(size)
    sent, failed = 0, 0
    print("ready", flush=True)
    for i in range(count):
        key = keys[i % len(keys)]
        try:
            session.get(key, lambda reply: None, payload=payload, timeout=5.0)
            session.put(key, payload)
            sent += 1
        except Exception:  # noqa: BLE001 - a closed link is an outcome, counted
            failed += 1
        time.sleep(0.2)
    print(json.dumps({"sent": sent, "failed": failed, "bytes": len(payload)}), flush=True)
    time.sleep(0.5)
    session.close()


def token(endpoint, lab, robot):
    session = client(endpoint)
    keys = [str(reply.ok.key_expr) for reply in session.liveliness().get(f"subsume/lab/{lab}/robot/{robot}/**", timeout=5.0) if reply.ok is not None]
    tokens = [session.liveliness().declare_token(key) for key in keys]
    print(json.dumps({"ready": keys}), flush=True)
    sys.stdin.read()
    for held in tokens:
        held.undeclare()
    print(json.dumps({"released": len(tokens)}), flush=True)
    session.close()


def main():
    command, args = sys.argv[1], sys.argv[2:]
    if command == "rogue":
        rogue(*args)
    elif command == "capture":
        capture(*args)
    elif command == "flood":
        flood(args[0], args[1], args[2], float(args[3]), float(args[4]))
    elif command == "oversized":
        oversized(args[0], args[1], args[2], int(args[3]), int(args[4]))
    elif command == "token":
        token(*args)
    else:
        sys.exit(f"unknown attack {command}")


if __name__ == "__main__":
    main()
