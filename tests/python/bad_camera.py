"""Three misbehaving IP cameras for tests/all/ipcam.rs, each an HTTP server
on its own loopback port streaming multipart/x-mixed-replace (MJPEG) as
an IP camera does, with its fault:

- garbage: each connection sends good frames alternating with parts that
  are not JPEG, then bytes with no multipart framing at all (the client
  must give the connection up and dial again);
- oversized: good frames alternating with parts larger than the camera's
  limit, announced by Content-Length or not;
- stall: three good frames on the first connection, then nothing while
  the connection stays open (and nothing at all on the next ones).

The good frames are 160x120 JPEGs made by Pillow (PyPI). Prints
`garbage PORT`, `oversized PORT`, `stall PORT` (one line each) and runs
until killed.

Usage: bad_camera.py OVERSIZED_BYTES
"""

import io
import socket
import sys
import threading
import time

from PIL import Image

BOUNDARY = b"cameraboundary"
RATE_HZ = 10.0


def jpeg() -> bytes:
    out = io.BytesIO()
    Image.new("RGB", (160, 120), (200, 40, 40)).save(out, format="JPEG", quality=80)
    return out.getvalue()


GOOD = jpeg()


def part(body: bytes, length: bool = True) -> bytes:
    head = b"--" + BOUNDARY + b"\r\nContent-Type: image/jpeg\r\n"
    if length:
        head += b"Content-Length: %d\r\n" % len(body)
    return head + b"\r\n" + body + b"\r\n"


def answer(conn: socket.socket) -> None:
    conn.settimeout(5)
    request = b""
    while b"\r\n\r\n" not in request:
        chunk = conn.recv(4096)
        if not chunk:
            raise ConnectionError("no request")
        request += chunk
    conn.sendall(
        b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary="
        + BOUNDARY
        + b"\r\nCache-Control: no-cache\r\n\r\n"
    )


def garbage(conn: socket.socket, _big: int) -> None:
    for _ in range(5):
        conn.sendall(part(GOOD))
        time.sleep(1 / RATE_HZ)
        conn.sendall(part(b"<html>this is not a picture</html>"))
        time.sleep(1 / RATE_HZ)
    conn.sendall(b"\x00\x17garbage without any framing " * 200)
    time.sleep(1.0)


def oversized(conn: socket.socket, big: int) -> None:
    body = b"\xff\xd8" + b"\x00" * (big - 4) + b"\xff\xd9"
    for i in range(1000):
        conn.sendall(part(GOOD))
        time.sleep(1 / RATE_HZ)
        conn.sendall(part(body, length=i % 2 == 0))
        time.sleep(1 / RATE_HZ)


STALLS = {"connections": 0}


def stall(conn: socket.socket, _big: int) -> None:
    STALLS["connections"] += 1
    if STALLS["connections"] == 1:
        for _ in range(3):
            conn.sendall(part(GOOD))
            time.sleep(1 / RATE_HZ)
    time.sleep(3600)


def serve(listener: socket.socket, behave, big: int) -> None:
    while True:
        conn, _ = listener.accept()

        def run(conn=conn):
            try:
                answer(conn)
                behave(conn, big)
            except OSError:
                pass
            finally:
                conn.close()

        threading.Thread(target=run, daemon=True).start()


def main() -> None:
    big = int(sys.argv[1])
    threads = []
    for name, behave in (("garbage", garbage), ("oversized", oversized), ("stall", stall)):
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        print(name, listener.getsockname()[1], flush=True)
        thread = threading.Thread(target=serve, args=(listener, behave, big), daemon=True)
        thread.start()
        threads.append(thread)
    for thread in threads:
        thread.join()


if __name__ == "__main__":
    main()
