"""Plays an iRobot Create 2 on a pseudo-terminal, checked against pycreate2.

    create2_peer.py LEFT_MM RIGHT_MM

The host is expected to drive at LEFT_MM / RIGHT_MM mm/s. pycreate2
(PyPI, 0.8.0; nobody here wrote it) is the reference: the bytes it writes
for Start, Safe, Stop and drive_direct are what the host must send, and its
packet-100 decoder (SensorPacketDecoder) fixes where each sensor's bytes lie
and how they read, so the stream frames built here from those bytes are
what a Create 2 sends.

The robot side follows the Open Interface: Drive Direct is obeyed in Safe
or Full mode only; a Stream (148) request starts frames `19 N [id data]...
checksum` every 15 ms. The wheels move at the commanded speeds, the encoder
counts follow them (pycreate2's ROBOT.TICK_TO_DISTANCE mm a count) and the
bumper is pressed from 0.3 s to 0.6 s after the stream started.

Summary (one JSON line): every byte received (hex), the reference frames,
the bytes left unparsed, and the pose after each frame by dead reckoning
(pycreate2's ROBOT.WHEEL_BASE), for the test to compare with the host's.
"""

import math
import struct
import sys

from pycreate2 import Create2
from pycreate2.OI import OPCODES, ROBOT
from pycreate2.createSerial import SerialCommandInterface
from pycreate2.packets import SensorPacketDecoder

import peer_common


class Recorder:
    """Stands in for pyserial: keeps what pycreate2 writes. Never "open",
    so pycreate2's destructor has nothing to close."""

    is_open = False

    def __init__(self):
        self.data = bytearray()

    def write(self, data):
        self.data += data

    def close(self):
        pass


class Reference(Create2):
    """pycreate2's API writing into a Recorder instead of a port."""

    def __init__(self):
        self.SCI = SerialCommandInterface.__new__(SerialCommandInterface)
        self.SCI.ser = Recorder()
        self.sleep_timer = 0

    def __del__(self):
        pass

    def take(self, call):
        call()
        data = bytes(self.SCI.ser.data)
        self.SCI.ser.data.clear()
        return data


# Where each streamed packet's bytes sit in packet 100 (80 bytes), as
# pycreate2's SensorPacketDecoder reads them.
PACKET_100_SLICES = {
    7: (0, 1),
    22: (17, 19),
    43: (52, 54),
    44: (54, 56),
    46: (57, 59),
    47: (59, 61),
    48: (61, 63),
    49: (63, 65),
    50: (65, 67),
    51: (67, 69),
}
LIGHT_BUMPS = [300, 600, 900, 1200, 1500, 1800]  # left .. right
VOLTS_MV = 14400
STREAM_PERIOD = 0.015
# Data bytes after each opcode the robot side reads (None: by count byte).
LENGTHS = {7: 0, 128: 0, 131: 0, 132: 0, 173: 0, 142: 1, 150: 1, 137: 4, 145: 4, 148: None, 149: None}


def packet_100(bumped, left_counts, right_counts):
    """A packet 100 with these readings, checked by pycreate2's decoder."""
    data = bytearray(80)
    data[0] = 0x03 if bumped else 0x00
    data[17:19] = struct.pack(">H", VOLTS_MV)
    data[52:54] = struct.pack(">H", left_counts)
    data[54:56] = struct.pack(">H", right_counts)
    for i, signal in enumerate(LIGHT_BUMPS):
        data[57 + 2 * i : 59 + 2 * i] = struct.pack(">H", signal)
    sensors = SensorPacketDecoder(bytes(data))
    assert sensors.bumps_wheeldrops.bump_left == bumped and sensors.bumps_wheeldrops.bump_right == bumped
    assert sensors.voltage == VOLTS_MV
    assert (sensors.encoder_counts_left, sensors.encoder_counts_right) == (left_counts, right_counts)
    assert sensors.light_bumper_left == LIGHT_BUMPS[0] and sensors.light_bumper_right == LIGHT_BUMPS[5]
    return bytes(data)


class Robot:
    def __init__(self):
        self.received = bytearray()
        self.pending = bytearray()
        self.unparsed = 0
        self.mode = "off"
        self.wheels = (0.0, 0.0)  # left, right mm/s
        self.travel = [0.0, 0.0]  # mm
        self.streamed = []
        self.stream_started = None
        self.last = None
        self.pose = [0.0, 0.0, 0.0]
        self.last_counts = None
        self.poses = []
        self.frames = 0

    def on_bytes(self, data):
        self.received += data
        self.pending += data
        while self.pending:
            opcode = self.pending[0]
            if opcode not in LENGTHS:
                self.unparsed += 1
                del self.pending[0]
                continue
            length = LENGTHS[opcode]
            if length is None:
                if len(self.pending) < 2:
                    return
                length = 1 + self.pending[1]
            if len(self.pending) < 1 + length:
                return
            data = bytes(self.pending[1 : 1 + length])
            del self.pending[: 1 + length]
            self.command(opcode, data)

    def command(self, opcode, data):
        if opcode == 128:
            self.mode = "passive"
            self.wheels = (0.0, 0.0)
        elif opcode in (131, 132) and self.mode != "off":
            self.mode = "safe" if opcode == 131 else "full"
        elif opcode in (7, 173):
            self.mode = "off"
            self.streamed = []
            self.wheels = (0.0, 0.0)
        elif opcode == 145 and self.mode in ("safe", "full"):
            right, left = struct.unpack(">2h", data)
            self.wheels = (float(left), float(right))
        elif opcode == 148 and self.mode != "off":
            self.streamed = list(data[1:])
            self.stream_started = self.last
        elif opcode == 150:
            if data[0] == 0:
                self.streamed = []

    def on_timer(self, now):
        if self.last is not None:
            dt = now - self.last
            self.travel[0] += self.wheels[0] * dt
            self.travel[1] += self.wheels[1] * dt
        self.last = now
        if not self.streamed or self.mode == "off":
            return
        if self.stream_started is None:
            self.stream_started = now
        since = now - self.stream_started
        counts = [int(round(t / ROBOT.TICK_TO_DISTANCE)) % 65536 for t in self.travel]
        full = packet_100(0.3 <= since <= 0.6, counts[0], counts[1])
        payload = bytearray()
        for packet in self.streamed:
            start, end = PACKET_100_SLICES[packet]
            payload.append(packet)
            payload += full[start:end]
        frame = bytearray([19, len(payload)]) + payload
        frame.append((-sum(frame)) & 0xFF)
        self.frames += 1
        self.dead_reckon(counts)
        self.pty.write(frame)

    def dead_reckon(self, counts):
        if self.last_counts is not None:
            d = []
            for new, old in zip(counts, self.last_counts):
                diff = (new - old) % 65536
                if diff >= 32768:
                    diff -= 65536
                d.append(diff * ROBOT.TICK_TO_DISTANCE / 1000.0)
            distance = (d[0] + d[1]) / 2
            turn = (d[1] - d[0]) / (ROBOT.WHEEL_BASE / 1000.0)
            mid = self.pose[2] + turn / 2
            self.pose[0] += distance * math.cos(mid)
            self.pose[1] += distance * math.sin(mid)
            self.pose[2] = math.atan2(math.sin(self.pose[2] + turn), math.cos(self.pose[2] + turn))
        self.last_counts = counts
        self.poses.append(list(self.pose))


def main():
    left_mm, right_mm = int(sys.argv[1]), int(sys.argv[2])
    reference = Reference()
    references = {
        "start": reference.take(lambda: reference.SCI.write(OPCODES.START)).hex(),
        "safe": reference.take(lambda: reference.SCI.write(OPCODES.SAFE)).hex(),
        "stop_oi": reference.take(lambda: reference.SCI.write(OPCODES.STOP)).hex(),
        # drive_direct takes the right wheel first.
        "drive": reference.take(lambda: reference.drive_direct(right_mm, left_mm)).hex(),
        "halt": reference.take(lambda: reference.drive_direct(0, 0)).hex(),
    }
    pty = peer_common.Pty()
    robot = Robot()
    robot.pty = pty
    peer_common.serve(pty, robot.on_bytes, robot.on_timer, STREAM_PERIOD)
    peer_common.finish(
        {
            "received": bytes(robot.received).hex(),
            "references": references,
            "unparsed": robot.unparsed,
            "frames": robot.frames,
            "poses": robot.poses,
            "light_bumps": LIGHT_BUMPS,
            "volts_mv": VOLTS_MV,
        }
    )


if __name__ == "__main__":
    main()
