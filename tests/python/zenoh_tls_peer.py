"""A Zenoh peer over TLS with user/password authentication, built on the
eclipse-zenoh package (tests/all/zenoh.rs drives it).

    zenoh_tls_peer.py ENDPOINT PKI_DIR

Listens on ENDPOINT (tls/HOST:PORT) with PKI_DIR/server.pem, server.key,
ca.pem and the user dictionary PKI_DIR/users.txt; it logs in as robot-a.
Prints "ready", then puts the scalar 2.5 in subsume's wire form (tag 2,
f64 little-endian) on test/tls/in every 50 ms and collects what arrives on
test/tls/out, until stdin closes; then prints a JSON summary.
"""

import json
import struct
import sys
import threading

import zenoh


def main():
    endpoint, pki = sys.argv[1], sys.argv[2]
    conf = zenoh.Config()
    settings = {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "listen/endpoints": [endpoint],
        "transport/link/tls/root_ca_certificate": f"{pki}/ca.pem",
        "transport/link/tls/listen_certificate": f"{pki}/server.pem",
        "transport/link/tls/listen_private_key": f"{pki}/server.key",
        "transport/auth/usrpwd/user": "robot-a",
        "transport/auth/usrpwd/password": "secret-a",
        "transport/auth/usrpwd/dictionary_file": f"{pki}/users.txt",
    }
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    session = zenoh.open(conf)
    lock = threading.Lock()
    state = {"received": [], "bad": []}

    def on_out(sample):
        raw = bytes(sample.payload.to_bytes())
        with lock:
            if len(raw) == 9 and raw[0] == 2:
                state["received"].append(struct.unpack("<d", raw[1:])[0])
            else:
                state["bad"].append(raw.hex())

    sub = session.declare_subscriber("test/tls/out", on_out)
    pub = session.declare_publisher("test/tls/in")
    print("ready", flush=True)
    done = threading.Event()

    def wait_for_stdin_close():
        sys.stdin.read()
        done.set()

    threading.Thread(target=wait_for_stdin_close, daemon=True).start()
    sent = 0
    while not done.wait(0.05):
        pub.put(bytes([2]) + struct.pack("<d", 2.5))
        sent += 1
    with lock:
        summary = {"received": state["received"], "bad": state["bad"], "sent": sent}
    del sub
    session.close()
    print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
