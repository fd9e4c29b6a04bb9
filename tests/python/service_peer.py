"""The other side of subsume's TLS listeners and /metrics, for tests/all/service.rs.

Every connection verifies the host's certificate against the test CA with
Python's own ssl module (OpenSSL), and /metrics is parsed by the text parser
of the prometheus_client package. Each command prints one JSON document.

    service_peer.py login URL CA USER PASSWORD
    service_peer.py metrics URL CA [TOKEN]
    service_peer.py teleop-lines HOST:PORT CA NAME TOKEN COMMANDS
    service_peer.py teleop-websocket HOST:PORT CA
    service_peer.py plain-http HOST:PORT
    service_peer.py get URL CA USER PASSWORD PATH...
"""

import base64
import json
import os
import socket
import ssl
import sys
import time
import urllib.error
import urllib.request

from prometheus_client.openmetrics.parser import text_string_to_metric_families


def context(ca):
    ctx = ssl.create_default_context(cafile=ca)
    return ctx


def request(url, ca, method="GET", body=None, token=None):
    headers = {"Content-Type": "application/json"} if body is not None else {}
    if token:
        headers["Authorization"] = "Bearer " + token
    req = urllib.request.Request(url, data=body, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, context=context(ca), timeout=30) as response:
            return response.status, dict(response.headers), response.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read().decode()


def login(url, ca, user, password):
    body = json.dumps({"name": user, "password": password}).encode()
    status, headers, text = request(url + "api/v1/login", ca, "POST", body)
    token = json.loads(text).get("token") if status == 200 else None
    return {"status": status, "set_cookie": headers.get("set-cookie", ""), "token": token}


def get(url, ca, user, password, *paths):
    """Logs in and reads each API path (`{set}` in a path is the active
    set's id, once /api/v1/status was read): their JSON answers."""
    token = login(url, ca, user, password)["token"]
    answers = []
    active = None
    for path in paths:
        status, _, text = request(url + path.lstrip("/").replace("{set}", str(active)), ca, token=token)
        answer = json.loads(text) if text else None
        if path.endswith("/status") and status == 200:
            active = answer.get("set")
        answers.append({"status": status, "json": answer})
    return answers


def metrics(url, ca, token=None):
    status, headers, text = request(url + "metrics", ca, token=token)
    out = {"status": status, "content_type": headers.get("content-type", ""), "families": {}}
    if status != 200:
        out["body"] = text
        return out
    for family in text_string_to_metric_families(text):
        out["families"][family.name] = {
            "type": family.type,
            "samples": [[s.name, s.labels, s.value] for s in family.samples],
        }
    return out


def read_line(stream):
    line = b""
    while not line.endswith(b"\n"):
        chunk = stream.recv(1)
        if not chunk:
            break
        line += chunk
    return line.decode().rstrip("\n")


def teleop_lines(address, ca, name, token, commands):
    """Logs in over TLS, answers pings, asks for direct mode, sends
    `commands` commands 20 ms apart; returns every line the host sent."""
    host, port = address.rsplit(":", 1)
    raw = socket.create_connection((host, int(port)), timeout=10)
    stream = context(ca).wrap_socket(raw, server_hostname=host)
    received = []
    out = {"tls_version": stream.version(), "lines": received}

    def next_line():
        line = read_line(stream)
        received.append(line)
        if line.startswith("PING "):
            stream.sendall(("PONG " + line.split(" ", 1)[1] + "\n").encode())
        return line

    next_line()  # HELLO
    stream.sendall(f"AUTH {name} {token}\n".encode())
    deadline = time.time() + 20
    while time.time() < deadline and not next_line().startswith("RTT "):
        pass
    stream.sendall(b"MODE direct\n")
    while time.time() < deadline and not next_line().startswith("MODE "):
        pass
    start = time.monotonic()
    for seq in range(1, commands + 1):
        ms = int((time.monotonic() - start) * 1000)
        stream.sendall(f"CMD {seq} {ms} VEL 0.1 0.0\n".encode())
        time.sleep(0.02)
    # Stay connected (answering pings) while the test scrapes /metrics.
    hold = float(os.environ.get("HOLD_SECONDS", "0"))
    stream.settimeout(0.2)
    until = time.time() + hold
    while time.time() < until:
        try:
            next_line()
        except (socket.timeout, TimeoutError):
            pass
    stream.settimeout(10)
    stream.sendall(b"QUIT\n")
    try:
        while next_line():
            pass
    except (OSError, ssl.SSLError):
        pass
    stream.close()
    return out


def teleop_websocket(address, ca):
    """Opens the teleoperation WebSocket over TLS by hand and reads the
    host's first message."""
    host, port = address.rsplit(":", 1)
    raw = socket.create_connection((host, int(port)), timeout=10)
    stream = context(ca).wrap_socket(raw, server_hostname=host)
    key = base64.b64encode(os.urandom(16)).decode()
    stream.sendall(
        (
            f"GET /teleop HTTP/1.1\r\nHost: {address}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = stream.recv(1)
        if not chunk:
            break
        head += chunk
    status = head.split(b"\r\n", 1)[0].decode()
    first = stream.recv(2)
    length = first[1] & 0x7F
    if length == 126:
        length = int.from_bytes(stream.recv(2), "big")
    payload = b""
    while len(payload) < length:
        payload += stream.recv(length - len(payload))
    stream.close()
    return {"status": status, "opcode": first[0] & 0x0F, "message": payload.decode()}


def plain_http(address):
    """Speaks plain HTTP to a TLS port: what comes back is no HTTP."""
    host, port = address.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        data = b""
        try:
            while True:
                chunk = s.recv(4096)
                if not chunk:
                    break
                data += chunk
        except OSError:
            pass
    return {"http": data.startswith(b"HTTP/"), "bytes": len(data)}


def main(argv):
    command, args = argv[1], argv[2:]
    if command == "login":
        result = login(*args)
    elif command == "metrics":
        result = metrics(*args)
    elif command == "teleop-lines":
        result = teleop_lines(args[0], args[1], args[2], args[3], int(args[4]))
    elif command == "teleop-websocket":
        result = teleop_websocket(*args)
    elif command == "plain-http":
        result = plain_http(*args)
    elif command == "get":
        result = get(*args)
    else:
        raise SystemExit(f"unknown command {command}")
    print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv)
