#!/usr/bin/env python3
"""Builds the seed corpora in tests/fuzz/corpus/<target>/ from real examples: the robot
protocol document's sessions, the shipped cell and part files, the test point clouds (cut to
a few hundred points), frames and PLY files as the camera driver writes them, PLC register
blocks from docs/plc-interface.md and CANopen traffic of the spindle start-up.

Run from anywhere: tests/fuzz/make_corpus.py (rewrites the corpus directories)."""
import math
import pathlib
import re
import shutil
import struct

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent.parent
CORPUS = HERE / "corpus"


def target(name):
    d = CORPUS / name
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    return d


def write(d, name, data):
    (d / name).write_bytes(data if isinstance(data, bytes) else data.encode())


# ---- robot protocol: the wire lines of docs/robot-protocol.md, as sessions
d = target("robot_protocol")
doc = (ROOT / "docs/robot-protocol.md").read_text()
lines = re.findall(r"^(\d{1,5} [A-Z]+(?: [^\n]*)?)$", doc, re.M)
write(d, "doc_lines", "\n".join(lines) + "\n")
write(d, "doc_lines_crlf", "\r\n".join(lines) + "\r\n")
fettle_side = [l for l in lines if l.split()[1] in ("HELLO", "TRAJ", "CHUNK", "P", "Q", "END", "RUN", "STOP", "RESET", "PING")]
robot_side = [l for l in lines if l not in fettle_side]
write(d, "fettle_to_robot", "\n".join(fettle_side) + "\n")
write(d, "robot_to_fettle", "\n".join(robot_side) + "\n")
write(d, "upload", "1 HELLO 1 cell-1 3000\n2 TRAJ 1 2 1 D575176B\n3 CHUNK 1 0 2\n"
      "4 P 0 450.000 -120.250 310.000 100.000 0 0 A\n5 Q 0 0.000000 1.000000 0.000000 0.000000\n"
      "6 P 1 450.000 -80.125 302.500 25.000 9000 1 G\n7 Q 1 0.000000 1.000000 0.000000 0.000000\n"
      "8 END 1\n9 RUN 1\n10 PING\n11 STOP\n12 RESET\n")
write(d, "replies", "1 ACK 1 1 sim-robot\n2 ACK 2\n3 NAK 3 CRC expected D575176B\n4 PONG 10\n"
      "5 PROG 1 1 1\n6 DONE 1 2\n7 FAULT 1 COLLISION contact at point 1\n8 FAULT 0 ESTOP\n")
write(d, "limits", "99999 P 99998 -99999.999 -99999.999 -99999.999 9999.999 99999 9999 R\n"
      "99999 Q 99998 -0.500000 -0.500000 -0.500000 -0.500000\n")
write(d, "too_long", "1 NAK 1 SYNTAX " + "x" * 90 + "\n2 PING\n")

# ---- config: the shipped cell files and part recipes (first byte: 0 auto, 1 cell, 2 part)
d = target("config")
for f in sorted((ROOT / "config").rglob("*.toml")):
    mode = b"\x02" if "parts" in f.parts else b"\x01"
    write(d, f.name, mode + f.read_bytes())
    write(d, "auto_" + f.name, b"\x00" + f.read_bytes())
# Nesting far beyond the parser's limit (64): refused before toml++ recurses (docs/security.md)
write(d, "auto_deep-dotted-header.toml", b"\x00[a" + b".b" * 50000 + b"]\nx = 1\n")
write(d, "cell_deep-inline-tables.toml", b"\x01v = " + b"{a = " * 2000 + b"1" + b"}" * 2000 + b"\n")


# ---- clouds (first byte: even PCD, odd PLY), cut to a few hundred points
def cut_pcd_ascii(text, keep):
    head, _, body = text.partition("DATA ascii\n")
    pts = body.splitlines()[:keep]
    head = re.sub(r"WIDTH \d+", f"WIDTH {len(pts)}", head)
    head = re.sub(r"HEIGHT \d+", "HEIGHT 1", head)
    head = re.sub(r"POINTS \d+", f"POINTS {len(pts)}", head)
    return head + "DATA ascii\n" + "\n".join(pts) + "\n"


d = target("cloud")
bun = (ROOT / "tests/data/bun4.pcd").read_text()
write(d, "bun4_cut.pcd", b"\x00" + cut_pcd_ascii(bun, 120).encode())
pts = [(math.cos(i * 0.3) * 50, math.sin(i * 0.3) * 50, i * 0.5) for i in range(64)]
binary = b"".join(struct.pack("<3f", *p) for p in pts)
pcd_head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            "WIDTH 64\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 64\nDATA binary\n")
write(d, "spiral_binary.pcd", b"\x00" + pcd_head.encode() + binary)
normals = b"".join(struct.pack("<6f", *p, 0.0, 0.0, 1.0) for p in pts)
write(d, "spiral_normals.pcd", b"\x00" + pcd_head.replace("FIELDS x y z", "FIELDS x y z normal_x normal_y normal_z")
      .replace("SIZE 4 4 4", "SIZE 4 4 4 4 4 4").replace("TYPE F F F", "TYPE F F F F F F")
      .replace("COUNT 1 1 1", "COUNT 1 1 1 1 1 1").encode() + normals)
def lzf(data):
    """LZF as PCL's binary_compressed PCD uses it: literal runs (ctrl = length - 1, up to 32)
    and back references (ctrl = (length - 2) << 5 | offset >> 8, then offset & 0xff; length
    over 8 takes an extra byte), found greedily through a 3-byte hash."""
    out, lit, seen, i = bytearray(), bytearray(), {}, 0

    def flush():
        for k in range(0, len(lit), 32):
            out.append(len(lit[k:k + 32]) - 1)
            out.extend(lit[k:k + 32])
        lit.clear()

    while i < len(data):
        key = data[i:i + 3]
        j = seen.get(key)
        seen[key] = i
        if len(key) == 3 and j is not None and i - j - 1 < 8192:
            n = 3
            while i + n < len(data) and n < 264 and data[j + n] == data[i + n]:
                n += 1
            flush()
            off = i - j - 1
            if n - 2 < 7:
                out += bytes([((n - 2) << 5) | (off >> 8), off & 0xFF])
            else:
                out += bytes([(7 << 5) | (off >> 8), n - 2 - 7, off & 0xFF])
            i += n
        else:
            lit.append(data[i])
            i += 1
    flush()
    return bytes(out)


# Organized 8 x 8 with an rgba field and a row of NaN points, binary_compressed (fields one
# after another: all x, all y, all z, all rgba).
grid = [(x * 2.0, y * 2.0, 600.0 + 0.1 * x) if y != 3 else (math.nan,) * 3 for y in range(8) for x in range(8)]
soa = b"".join(struct.pack("<64f", *[p[k] for p in grid]) for k in range(3)) + struct.pack("<64I", *[0xFF8040] * 64)
write(d, "organized_compressed.pcd", b"\x00" + ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgba\nSIZE 4 4 4 4\n"
      "TYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 8\nHEIGHT 8\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 64\n"
      "DATA binary_compressed\n").encode() + struct.pack("<II", len(lzf(soa)), len(soa)) + lzf(soa))
kitti = (ROOT / "tests/data/kitti_source.ply").read_bytes()
head_end = kitti.index(b"end_header\n") + len(b"end_header\n")
head = kitti[:head_end].decode()
stride = 4 * len(re.findall(r"^property float", head, re.M))
keep = 150
head = re.sub(r"element vertex \d+", f"element vertex {keep}", head)
write(d, "kitti_cut.ply", b"\x01" + head.encode() + kitti[head_end:head_end + keep * stride])
ply_ascii = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n" \
            "property float nx\nproperty float ny\nproperty float nz\nend_header\n" + \
            "".join(f"{p[0]:.3f} {p[1]:.3f} {p[2]:.3f} 0 0 1\n" for p in pts[:4])
write(d, "ascii_normals.ply", b"\x01" + ply_ascii.encode())
write(d, "nan_inf.ply", b"\x01" + b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
      b"property float y\nproperty float z\nend_header\n" +
      struct.pack("<9f", float("nan"), 0, 0, float("inf"), 1, 2, 3, 4, 5))


# ---- PLY as fettle::write_ply writes an organized cloud (NaN = no data)
def organized_ply(w, h):
    data = b""
    for v in range(h):
        for u in range(w):
            z = float("nan") if (u + v) % 5 == 0 else 400.0 + u + v
            data += struct.pack("<3f", (u - w / 2) * 0.5, (v - h / 2) * 0.5, z)
    head = ("ply\nformat binary_little_endian 1.0\ncomment fettle organized cloud, millimetres, camera frame, "
            f"NaN = no data\nobj_info num_cols {w}\nobj_info num_rows {h}\nelement vertex {w * h}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n")
    return head.encode() + data


d = target("camera_ply")
write(d, "organized_8x6.ply", organized_ply(8, 6))
write(d, "organized_1x1.ply", organized_ply(1, 1))
write(d, "unorganized.ply", organized_ply(5, 4).replace(b"obj_info num_rows 4\n", b""))

# ---- camera frames: selector (format % 4: C16, C32f, ABC32f, Mono16), narrow sizes, Scan3d params, payload
d = target("camera_decode")


def frame(selector, w, h, payload, scale=0.05, offset=300.0, flag=True, invalid=0.0, inch=False, intr=True):
    b = bytes([selector, 0, w, h]) + struct.pack("<dd", scale, offset) + bytes([1 if flag else 0])
    b += struct.pack("<d", invalid) + bytes([1 if inch else 0, 1 if intr else 0])
    if intr:
        b += struct.pack("<4d", 500.0, 500.0, w / 2, h / 2)
    return b + payload


w, h = 8, 6
c16 = b"".join(struct.pack("<H", 0 if (u * v) % 7 == 3 else 2000 + u * 10 + v) for v in range(h) for u in range(w))
c32 = b"".join(struct.pack("<f", float("nan") if (u + v) % 9 == 0 else 400.0 + u) for v in range(h) for u in range(w))
abc = b"".join(struct.pack("<3f", u - 4.0, v - 3.0, 450.0 + u * v) for v in range(h) for u in range(w))
write(d, "c16_8x6", frame(0, w, h, c16))
write(d, "c32f_8x6", frame(1, w, h, c32, flag=False))
write(d, "abc32f_8x6", frame(2, w, h, abc, invalid=0.0))
write(d, "c16_no_intrinsics", frame(0, w, h, c16, intr=False))
write(d, "c16_inch_short", frame(0, w, h, c16[:40], inch=True))
write(d, "mono16", frame(3, w, h, c16))

# ---- PLC register blocks (first int16: photo positions); docs/plc-interface.md
d = target("plc_registers")


def regs(limit, values):
    return struct.pack("<h", limit) + b"".join(struct.pack("<H", v) for v in values)


write(d, "plc_idle", regs(3, [1, 17, 0, 0, 1, 0, 0, 0]))
write(d, "plc_request", regs(3, [1, 18, 1, 42, 2, 2, 2, 1]))
write(d, "plc_moving", regs(3, [1, 19, 1, 42, 3, 3, 1, 0]))
write(d, "plc_bad_state", regs(3, [1, 20, 1, 42, 9, 7, 6, 2]))
write(d, "fettle_idle", regs(3, [100, 0, 2, 0, 0, 0, 0, 0, 0, 0]))
write(d, "fettle_fault", regs(3, [101, 1, 11, 1, 1, 2, 1, 1203, 1, 1]))
write(d, "short_block", regs(16, [1, 2, 3]))

# ---- Modbus TCP replies: request (write?, transaction, unit, address, count - 1) + reply ADU
d = target("modbus_reply")


def mbap(t, unit, pdu, protocol=0, length=None):
    return struct.pack(">HHHB", t, protocol, len(pdu) + 1 if length is None else length, unit) + pdu


def read_case(t, unit, address, count, reply):
    return b"\x00" + struct.pack("<HBH", t, unit, address) + bytes([count - 1]) + reply


def write_case(t, unit, address, count, reply):
    return b"\x01" + struct.pack("<HBH", t, unit, address) + bytes([count - 1]) + reply


plc_block = bytes([0x03, 20]) + b"".join(struct.pack(">H", v) for v in [2, 17, 1, 42, 2, 2, 2, 1, 0, 0])
write(d, "read_good", read_case(1, 1, 0, 10, mbap(1, 1, plc_block)))
write(d, "read_protocol_7", read_case(2, 1, 0, 10, mbap(2, 1, plc_block, protocol=7)))
write(d, "read_other_unit", read_case(3, 1, 0, 10, mbap(3, 2, plc_block)))
write(d, "read_mbap_length_2", read_case(4, 1, 0, 10, mbap(4, 1, plc_block, length=2)))
write(d, "read_mbap_length_ffff", read_case(5, 1, 0, 10, mbap(5, 1, plc_block, length=0xFFFF)))
write(d, "read_exception", read_case(6, 1, 0, 10, mbap(6, 1, b"\x83\x02")))
write(d, "write_good", write_case(7, 1, 16, 10, mbap(7, 1, struct.pack(">BHH", 0x10, 16, 10))))
write(d, "write_other_address", write_case(8, 1, 16, 10, mbap(8, 1, struct.pack(">BHH", 0x10, 17, 10))))

# ---- CANopen: first byte even = socketcand stream, odd = raw frames on the bus
d = target("canopen")
write(d, "socketcand_session", b"\x00< hi >< ok >< ok >< frame 701 0.000100 00 >"
      b"< frame 581 0.010000 6017100064000000 >< frame 181 12.000345 3706 >"
      b"< send 601 8 40 41 60 00 00 00 00 00 >< send 000 2 81 01 >< frame 81 1.0 1023100000000000 >"
      b"< frame 1ABCDEF0 2.000001 >< frame 701 3.5 7F >")
write(d, "socketcand_garbage", b"\x00garbage< frame xyz 1 00 >< send 601 9 >< frame 181 1.0 123 >< open")


def can(base_index, payload, flags=0, any_id=None):
    f = bytes([flags | (4 if any_id is not None else 0)])
    f += struct.pack("<H", any_id if any_id is not None else base_index)
    return f + bytes([len(payload)]) + bytes(payload)


# bases: 0 NMT, 1 EMCY, 2 TPDO1, 3 SDO tx (drive->master), 4 SDO rx, 5 heartbeat (node 1)
boot = can(5, [0x00])
sdo_ok = can(3, [0x60, 0x17, 0x10, 0x00, 0, 0, 0, 0])
sdo_value = can(3, [0x4B, 0x41, 0x60, 0x00, 0x37, 0x06, 0, 0])
sdo_abort = can(3, [0x80, 0x00, 0x60, 0x00, 0x00, 0x00, 0x02, 0x06])
tpdo = can(2, [0x37, 0x06, 0xB8, 0x0B, 0x00, 0x00, 0x20, 0x01])
emcy = can(1, [0x10, 0x23, 0x03, 0, 0, 0, 0, 0])
hb_op = can(5, [0x05])
write(d, "drive_startup", b"\x01" + boot + sdo_ok * 6 + hb_op + tpdo)
write(d, "drive_fault", b"\x01" + boot + sdo_ok + tpdo + emcy + can(2, [0x08, 0x00, 0, 0, 0, 0, 0, 0]))
write(d, "drive_abort", b"\x01" + boot + sdo_abort + sdo_value + can(0, [0x81, 0x00]))
write(d, "master_to_drive", b"\x01" + can(4, [0x2B, 0x40, 0x60, 0x00, 0x0F, 0x00, 0, 0]) +
      can(4, [0x40, 0x41, 0x60, 0x00, 0, 0, 0, 0]) + can(0, [0x01, 0x01]) + can(0, [0x80, 0x00]))
# ---- control socket: request lines as `fettle` and scripts send them (docs/daemon-control.md).
# Header: read size (1..64), max_line_bytes (uint16, 16 + value % 1024), maintenance (bit 0).
d = target("control")


def control(name, chunk, max_line, maintenance, stream):
    write(d, name, bytes([chunk]) + struct.pack("<H", max_line) + bytes([maintenance]) + stream)


control("status", 7, 1000, 0, b'{"cmd":"status","id":1}\n')
control("cycles", 3, 1000, 0, b'{"cmd":"cycles","limit":20}\n{"cmd":"last_cycle"}\n')
control("maintenance_hold", 11, 1000, 0,
        b'{"cmd":"hold"}\n{"cmd":"maintenance","on":true}\n{"cmd":"hold"}\n{"cmd":"unhold"}\r\n'
        b'{"cmd":"reset"}\n{"cmd":"dry_cycle","id":"x"}\n')
control("bad", 1, 1000, 1, b'not json\n[1,2]\n{"cmd":5}\n{"cmd":"cycles","limit":-1}\n{"cmd":"nope"}\n\n   \n'
        b'{"cmd":"maintenance","on":"yes"}\n')
control("oversize", 5, 40, 0, b'{"cmd":"status","pad":"' + b"x" * 100 + b'"}\n{"cmd":"status"}\n' + b"y" * 90)

print("corpora written to", CORPUS)
