"""Plays a Basicmicro RoboClaw (packet serial) on a pseudo-terminal, checked
against the basicmicro package.

    roboclaw_peer.py ADDRESS M1_QPPS M2_QPPS [LAG_S] [STATUS]

The host is expected to drive M1/M2 at these encoder speeds (counts/s).
basicmicro (PyPI, 2.0.10; nobody here wrote it) is the reference: the bytes
its SpeedM1M2 (command 37 with its CRC16), GetEncoders (78) and
ReadMainBatteryVoltage (24) and ReadError (90, "read status") write are what
the host must send, and every encoder, battery or status answer sent here is
first read back through its GetEncoders, ReadMainBatteryVoltage or ReadError,
CRC check included.

The controller side: a write (37) with a good CRC is answered 0xFF (ACK)
and sets the speeds; a bad CRC gets no answer, as on the RoboClaw. A read
(78) is answered `enc1 enc2 crc`; a read of the main battery (24),
`volts crc` (12.4 V); a read of the status (90), `status crc` with the
STATUS bits (default 0: no error or warning). The counters follow the
speeds. With
LAG_S, every answer leaves that many seconds after its request (a slow
controller or adapter).

Summary (one JSON line): every byte received (hex), the reference frames,
counts of good writes, bad CRCs, reads and unparsed bytes, and the counters
after each read.
"""

import struct
import sys
import time

from basicmicro import Basicmicro

import peer_common

MIXED_SPEED = 37
READ_ENCODERS = 78
READ_MAIN_BATTERY = 24
READ_STATUS = 90
# The main battery this controller reports, tenths of a volt (12.4 V).
BATTERY_TENTHS = 124
TICK = 0.005


class FakePort:
    """Stands in for pyserial under basicmicro: keeps what it writes and
    answers its reads from `answer`."""

    is_open = True

    def __init__(self):
        self.written = bytearray()
        self.answer = bytearray(b"\xff")

    def write(self, data):
        self.written += data

    def read(self, n):
        data = bytes(self.answer[:n])
        del self.answer[:n]
        return data

    def flushInput(self):
        pass

    def reset_input_buffer(self):
        pass

    def close(self):
        pass


def reference():
    claw = Basicmicro("/dev/null", 38400)
    claw._port = FakePort()
    claw._connected = True
    return claw


def take(claw, call):
    claw._port.written.clear()
    claw._port.answer = bytearray(b"\xff")
    call()
    return bytes(claw._port.written)


def read_request(claw, address):
    """What GetEncoders writes, given a good answer (zero counters)."""
    claw._port.written.clear()
    zeros = bytes(8)
    claw._port.answer = bytearray(zeros + struct.pack(">H", crc16(claw, bytes([address, READ_ENCODERS]) + zeros)))
    ok, _, _ = claw.GetEncoders(address)
    assert ok
    return bytes(claw._port.written)


def battery_request(claw, address):
    """What ReadMainBatteryVoltage writes, given a good answer."""
    claw._port.written.clear()
    data = struct.pack(">H", BATTERY_TENTHS)
    claw._port.answer = bytearray(data + struct.pack(">H", crc16(claw, bytes([address, READ_MAIN_BATTERY]) + data)))
    ok, tenths = claw.ReadMainBatteryVoltage(address)
    assert ok and tenths == BATTERY_TENTHS, (ok, tenths)
    return bytes(claw._port.written)


def status_request(claw, address, status):
    """What ReadError writes, given a good answer of `status`."""
    claw._port.written.clear()
    data = struct.pack(">I", status)
    claw._port.answer = bytearray(data + struct.pack(">H", crc16(claw, bytes([address, READ_STATUS]) + data)))
    ok, read = claw.ReadError(address)
    assert ok and read == status, (ok, read)
    return bytes(claw._port.written)


def crc16(claw, data):
    claw.crc_clear()
    for byte in data:
        claw.crc_update(byte)
    return claw._crc & 0xFFFF


class Controller:
    def __init__(self, address, claw, lag=0.0, status=0):
        self.address = address
        self.status = status
        self.status_reads = 0
        self.claw = claw
        # A slow controller (or a slow USB adapter): every answer goes out
        # `lag` seconds after its request, in order.
        self.lag = lag
        self.outbox = []
        self.received = bytearray()
        self.pending = bytearray()
        self.speeds = [0, 0]
        self.counts = [0.0, 0.0]
        self.last = None
        self.writes = 0
        self.bad_crc = 0
        self.reads = 0
        self.battery_reads = 0
        self.unparsed = 0
        self.readings = []

    def on_bytes(self, data):
        self.received += data
        self.pending += data
        while len(self.pending) >= 2:
            address, command = self.pending[0], self.pending[1]
            if address != self.address or command not in (MIXED_SPEED, READ_ENCODERS, READ_MAIN_BATTERY, READ_STATUS):
                self.unparsed += 1
                del self.pending[0]
                continue
            if command == READ_ENCODERS:
                del self.pending[:2]
                self.answer_read()
                continue
            if command == READ_MAIN_BATTERY:
                del self.pending[:2]
                self.answer_battery()
                continue
            if command == READ_STATUS:
                del self.pending[:2]
                self.answer_status()
                continue
            if len(self.pending) < 12:
                return
            packet = bytes(self.pending[:12])
            if crc16(self.claw, packet[:10]) != struct.unpack(">H", packet[10:])[0]:
                self.bad_crc += 1
                del self.pending[0]
                continue
            del self.pending[:12]
            self.speeds = list(struct.unpack(">2i", packet[2:10]))
            self.writes += 1
            self.send(b"\xff")

    def answer_read(self):
        self.advance()
        enc = [int(round(c)) & 0xFFFFFFFF for c in self.counts]
        data = struct.pack(">2I", *enc)
        crc = crc16(self.claw, bytes([self.address, READ_ENCODERS]) + data)
        answer = data + struct.pack(">H", crc)
        # basicmicro must read the answer back as these counters.
        self.claw._port.answer = bytearray(answer)
        ok, enc1, enc2 = self.claw.GetEncoders(self.address)
        assert ok and (enc1, enc2) == tuple(enc), (ok, enc1, enc2, enc)
        self.reads += 1
        self.readings.append(enc)
        self.send(answer)

    def answer_battery(self):
        data = struct.pack(">H", BATTERY_TENTHS)
        answer = data + struct.pack(">H", crc16(self.claw, bytes([self.address, READ_MAIN_BATTERY]) + data))
        # basicmicro must read the answer back as this voltage.
        self.claw._port.answer = bytearray(answer)
        ok, tenths = self.claw.ReadMainBatteryVoltage(self.address)
        assert ok and tenths == BATTERY_TENTHS, (ok, tenths)
        self.battery_reads += 1
        self.send(answer)

    def answer_status(self):
        data = struct.pack(">I", self.status)
        answer = data + struct.pack(">H", crc16(self.claw, bytes([self.address, READ_STATUS]) + data))
        # basicmicro must read the answer back as this status.
        self.claw._port.answer = bytearray(answer)
        ok, status = self.claw.ReadError(self.address)
        assert ok and status == self.status, (ok, status, self.status)
        self.status_reads += 1
        self.send(answer)

    def send(self, data):
        if self.lag <= 0:
            self.pty.write(data)
        else:
            self.outbox.append((time.monotonic() + self.lag, data))

    def advance(self, now=None):
        now = time.monotonic() if now is None else now
        if self.last is not None:
            for i in range(2):
                self.counts[i] += self.speeds[i] * (now - self.last)
        self.last = now

    def on_timer(self, now):
        self.advance(now)
        while self.outbox and self.outbox[0][0] <= now:
            self.pty.write(self.outbox.pop(0)[1])


def main():
    address, m1, m2 = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    lag = float(sys.argv[4]) if len(sys.argv) > 4 else 0.0
    status = int(sys.argv[5], 0) if len(sys.argv) > 5 else 0
    claw = reference()
    references = {
        "drive": take(claw, lambda: claw.SpeedM1M2(address, m1, m2)).hex(),
        "halt": take(claw, lambda: claw.SpeedM1M2(address, 0, 0)).hex(),
        "read": read_request(claw, address).hex(),
        "battery": battery_request(claw, address).hex(),
        "status": status_request(claw, address, status).hex(),
    }
    pty = peer_common.Pty()
    controller = Controller(address, claw, lag, status)
    controller.pty = pty
    peer_common.serve(pty, controller.on_bytes, controller.on_timer, TICK)
    peer_common.finish(
        {
            "received": bytes(controller.received).hex(),
            "references": references,
            "writes": controller.writes,
            "bad_crc": controller.bad_crc,
            "reads": controller.reads,
            "battery_reads": controller.battery_reads,
            "status_reads": controller.status_reads,
            "unparsed": controller.unparsed,
            "readings": controller.readings,
        }
    )


if __name__ == "__main__":
    main()
