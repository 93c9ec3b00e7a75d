#!/usr/bin/env python3
"""imd_probe: a small IMD receiver (v2 or v3, from the IMD specification) to check a haptree IMD
server without VMD: connects, sends IMD_GO, counts frames for --seconds, optionally pulls one atom,
and prints what it saw. Standard library only.

  python3 tools/imd_probe.py --port 8888 --seconds 5 [--rate 2] [--pull ATOM FX FY FZ]

--pull forces are in the receiver's unit: kcal/(mol A) for v2 (VMD), kJ/(mol A) for v3."""
import argparse
import socket
import struct
import sys
import time


def read_exact(s, n):
    b = bytearray()
    while len(b) < n:
        chunk = s.recv(n - len(b))
        if not chunk:
            raise EOFError("server closed the connection")
        b += chunk
    return bytes(b)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8888)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rate", type=int, default=0, help="IMD_TRATE to send (0: keep the server's)")
    ap.add_argument("--pull", nargs=4, metavar=("ATOM", "FX", "FY", "FZ"))
    a = ap.parse_args()
    s = socket.create_connection((a.host, a.port), timeout=10)
    h = read_exact(s, 8)
    if struct.unpack(">i", h[:4])[0] != 4:
        sys.exit("imd_probe: the first packet is not a handshake")
    little = struct.unpack("<i", h[4:])[0]
    order = "<" if little in (2, 3) else ">"
    version = struct.unpack(order + "i", h[4:])[0]
    flags = None
    if version >= 3:
        t, n = struct.unpack(">ii", read_exact(s, 8))
        flags = read_exact(s, n)
    s.sendall(struct.pack(">ii", 3, 0))
    if a.rate:
        s.sendall(struct.pack(">ii", 8, a.rate))
    if a.pull:
        atom, f = int(a.pull[0]), [float(v) for v in a.pull[1:]]
        s.sendall(struct.pack(">ii", 6, 1) + struct.pack(order + "i3f", atom, *f))
    frames, natoms, first, last, step0, step1 = 0, 0, None, None, None, None
    end = time.monotonic() + a.seconds
    while time.monotonic() < end:
        t, n = struct.unpack(">ii", read_exact(s, 8))
        if t == 12:
            _, _, step = struct.unpack(order + "ddq", read_exact(s, 24))
            step0 = step if step0 is None else step0
            step1 = step
        elif t in (2, 14, 15):
            body = read_exact(s, 12 * n)
            if t == 2:
                frames += 1
                natoms = n
                xyz = struct.unpack(order + "3f", body[:12]) if not a.pull else struct.unpack(
                    order + "3f", body[12 * int(a.pull[0]):12 * int(a.pull[0]) + 12])
                first = first or xyz
                last = xyz
        else:
            sys.exit(f"imd_probe: unexpected packet type {t}")
    s.sendall(struct.pack(">ii", 0, 0))
    s.close()
    print(f"IMD v{version}, {natoms} atoms, {frames} frames in {a.seconds:g} s ({frames / a.seconds:.1f}/s)"
          + (f", session info {list(flags)}" if flags else "")
          + (f", steps {step0}..{step1}" if step0 is not None else ""))
    if first and last:
        label = f"atom {a.pull[0]}" if a.pull else "atom 0"
        print(f"{label}: first {tuple(round(v, 3) for v in first)} A, last {tuple(round(v, 3) for v in last)} A")


if __name__ == "__main__":
    main()
