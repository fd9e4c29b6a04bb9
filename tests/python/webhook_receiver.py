"""A webhook receiver for tests/all/lab.rs: Python's http.server and hmac,
an implementation no one here wrote, on the other side of subsume's signed
POSTs.

Usage: webhook_receiver.py SECRET OUT_FILE [--port N] [--fail N] [--tls CERT KEY]

Prints "listening on PORT" once bound to 127.0.0.1. Each POST is checked the
way docs/lab.md tells receivers to (HMAC-SHA256 over TIMESTAMP.BODY with
the hook's secret, compared in constant time) and appended to OUT_FILE as
one JSON line {"valid": bool, "event_id": header, "body": parsed body}. The
first N POSTs are answered 500 (and still written, with "answered": 500),
the others 200. With --tls, it serves HTTPS with that certificate chain and
key (Python's ssl module).
"""

import argparse
import hashlib
import hmac
import json
import ssl
import sys
from http.server import HTTPServer, BaseHTTPRequestHandler

parser = argparse.ArgumentParser()
parser.add_argument("secret")
parser.add_argument("out")
parser.add_argument("--port", type=int, default=0)
parser.add_argument("--fail", type=int, default=0)
parser.add_argument("--tls", nargs=2, metavar=("CERT", "KEY"))
args = parser.parse_args()
state = {"posts": 0}


def verify(secret, timestamp, body, signature):
    expected = "sha256=" + hmac.new(secret, timestamp + b"." + body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(expected, signature)


class Receiver(BaseHTTPRequestHandler):
    def do_POST(self):
        body = self.rfile.read(int(self.headers["Content-Length"]))
        valid = verify(
            args.secret.encode(),
            self.headers.get("X-Subsume-Timestamp", "").encode(),
            body,
            self.headers.get("X-Subsume-Signature", ""),
        )
        state["posts"] += 1
        answer = 500 if state["posts"] <= args.fail else 200
        line = {
            "valid": valid,
            "answered": answer,
            "event_id": self.headers.get("X-Subsume-Event-Id"),
            "body": json.loads(body),
        }
        with open(args.out, "a") as out:
            out.write(json.dumps(line) + "\n")
        self.send_response(answer)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *a):
        pass


server = HTTPServer(("127.0.0.1", args.port), Receiver)
if args.tls:
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(*args.tls)
    server.socket = context.wrap_socket(server.socket, server_side=True)
print(f"listening on {server.server_address[1]}", flush=True)
server.serve_forever()
