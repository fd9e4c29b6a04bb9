"""An SMTP server for tests/all/lab.rs: aiosmtpd, an implementation no one
here wrote, on the other side of subsume's mail (lettre on rustls).

Usage: smtp_receiver.py OUT_FILE --cert CERT --key KEY --user U --password P [--fail N]

Listens on 127.0.0.1 with STARTTLS required and AUTH (PLAIN/LOGIN) allowed
only under TLS, for the one user given; prints "listening on PORT" once
bound. Each message accepted is appended to OUT_FILE as one JSON line
{"from", "to", "subject", "body", "tls", "login"}. The first N messages
are answered 451 (try again later) and not written.
"""

import argparse
import email
import email.policy
import json
import socket
import ssl
import sys
import time

from aiosmtpd.controller import Controller
from aiosmtpd.smtp import AuthResult, LoginPassword

parser = argparse.ArgumentParser()
parser.add_argument("out")
parser.add_argument("--cert", required=True)
parser.add_argument("--key", required=True)
parser.add_argument("--user", required=True)
parser.add_argument("--password", required=True)
parser.add_argument("--fail", type=int, default=0)
args = parser.parse_args()
state = {"messages": 0}


def authenticate(server, session, envelope, mechanism, auth_data):
    ok = isinstance(auth_data, LoginPassword) and (
        auth_data.login.decode() == args.user and auth_data.password.decode() == args.password
    )
    return AuthResult(success=ok)


class Handler:
    async def handle_DATA(self, server, session, envelope):
        state["messages"] += 1
        if state["messages"] <= args.fail:
            return "451 4.3.0 try again later"
        message = email.message_from_bytes(envelope.content, policy=email.policy.default)
        line = {
            "from": envelope.mail_from,
            "to": envelope.rcpt_tos,
            "subject": str(message["subject"]),
            "body": message.get_content(),
            "tls": session.ssl is not None,
            "login": session.authenticated and args.user,
        }
        with open(args.out, "a") as out:
            out.write(json.dumps(line) + "\n")
        return "250 OK"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
context.load_cert_chain(args.cert, args.key)
port = free_port()
controller = Controller(
    Handler(),
    hostname="127.0.0.1",
    port=port,
    server_hostname="localhost",
    tls_context=context,
    require_starttls=True,
    authenticator=authenticate,
    auth_require_tls=True,
)
controller.start()
print(f"listening on {port}", flush=True)
try:
    while True:
        time.sleep(3600)
except KeyboardInterrupt:
    controller.stop()
