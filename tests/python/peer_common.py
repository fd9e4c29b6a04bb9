"""The pseudo-terminal side shared by the motor-controller peers.

A peer creates a PTY pair, prints the slave's path on its first stdout
line (the device the test hands subsume), and then plays the motor
controller on the master end: `serve(on_bytes, on_timer)` reads what the
host writes, calls `on_timer` every `period` seconds, and returns when stdin
closes (the test is done) or after `limit` seconds. The peer then prints
one JSON summary line for the test to check.
"""

import json
import os
import select
import sys
import time
import tty


class Pty:
    def __init__(self):
        self.master, self.slave = os.openpty()
        # Raw both ways until the host configures its end (it sets raw too).
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)

    def write(self, data):
        os.write(self.master, bytes(data))


def serve(pty, on_bytes, on_timer, period, limit=60.0):
    """Reads the host's bytes and runs the controller's clock until stdin
    closes or `limit` seconds pass."""
    print(pty.path, flush=True)
    deadline = time.monotonic() + limit
    next_tick = time.monotonic() + period
    stdin = sys.stdin.fileno()
    while time.monotonic() < deadline:
        timeout = max(0.0, next_tick - time.monotonic())
        readable, _, _ = select.select([pty.master, stdin], [], [], timeout)
        if pty.master in readable:
            try:
                data = os.read(pty.master, 4096)
            except OSError:
                # The host has the slave closed for a moment (reconnecting).
                data = b""
            if data:
                on_bytes(data)
        if stdin in readable and not os.read(stdin, 1024):
            break
        now = time.monotonic()
        if now >= next_tick:
            next_tick = now + period
            on_timer(now)
    # Whatever the host wrote last (its final STOP and closing bytes).
    while True:
        readable, _, _ = select.select([pty.master], [], [], 0.2)
        if not readable:
            break
        try:
            data = os.read(pty.master, 4096)
        except OSError:
            break
        if not data:
            break
        on_bytes(data)


def finish(summary):
    print(json.dumps(summary), flush=True)
