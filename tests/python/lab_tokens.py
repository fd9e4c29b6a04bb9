"""Lists a subsume lab's robots from their Zenoh liveliness tokens, with the
eclipse-zenoh package (tests/all/labnet.rs drives it).

    lab_tokens.py ENDPOINT LAB

Opens a client session to ENDPOINT (the lab server's tcp/HOST:PORT), asks
for the liveliness tokens under subsume/lab/LAB/robot/**, and prints each
one's key expression and the JSON body it carries (hex in the key), one
JSON object per line.
"""

import json
import os
import sys

import zenoh


def client(endpoint, user=None, password=None):
    """A Zenoh client session to `endpoint` only (no scouting), as `user`
    with `password` when given (a router's user/password authentication).
    A tls/ endpoint's certificate is checked against the authority in the
    PEM file $ZENOH_ROOT_CA when it is set."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if os.environ.get("ZENOH_ROOT_CA"):
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(os.environ["ZENOH_ROOT_CA"]))
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(conf)


def main():
    endpoint, lab = sys.argv[1], sys.argv[2]
    session = client(endpoint)
    try:
        for reply in session.liveliness().get(f"subsume/lab/{lab}/robot/**", timeout=5.0):
            key = str(reply.ok.key_expr)
            parts = key.split("/")
            # subsume/lab/LAB/robot/NAME/STATE/HEX/TAG
            body = json.loads(bytes.fromhex(parts[6]))
            print(json.dumps({"key": key, "name": parts[4], "state": parts[5], "body": body}), flush=True)
    finally:
        session.close()


if __name__ == "__main__":
    main()
