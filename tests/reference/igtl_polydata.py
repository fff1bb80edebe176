#!/usr/bin/env python3
"""An OpenIGTLink POLYDATA decoder written here from the specification alone
(openigtlink.org, Documents/Protocol/polydata.md and header.md, protocol 3.0), independent of the
bridge's Rust codec, to check what the bridge sends.

Usage: igtl_polydata.py MESSAGE.bin EXPECTED.json
MESSAGE.bin: one whole OpenIGTLink message (58-byte header + body) as the bridge sent it.
EXPECTED.json: {"device": str, "points": [[x, y, z], ...], "triangles": [[a, b, c], ...],
"displacement": [[dx, dy, dz], ...], optional "uncertainty_mm": [b, ...]} (float64; compared to
1e-4 mm after float32 decoding; with "uncertainty_mm", a point scalar of that name must match).
Checks the header (version 1 or 2, type POLYDATA, body size), the CRC-64 (ECMA-182 polynomial,
computed bit by bit), the counts and sizes of every section, and the values. Prints a summary;
exits non-zero on the first disagreement.
"""
import json
import struct
import sys

POLY = 0x42F0E1EBA9EA3693


def crc64(data):
    crc = 0
    for byte in data:
        crc ^= byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ POLY) if crc & (1 << 63) else (crc << 1)
            crc &= (1 << 64) - 1
    return crc


def fail(msg):
    print(f"igtl_polydata: FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def cstr(b):
    return b.split(b"\0", 1)[0].decode("ascii")


def main():
    raw = open(sys.argv[1], "rb").read()
    want = json.load(open(sys.argv[2]))
    if len(raw) < 58:
        fail("shorter than a header")
    version, mtype, device, _ts, body_size, crc = struct.unpack(">H12s20sQQQ", raw[:58])
    if version not in (1, 2):
        fail(f"header version {version}")
    if cstr(mtype) != "POLYDATA":
        fail(f"type {cstr(mtype)!r}")
    if cstr(device) != want["device"]:
        fail(f"device {cstr(device)!r}, expected {want['device']!r}")
    body = raw[58:]
    if len(body) != body_size:
        fail(f"BODY_SIZE {body_size}, {len(body)} bytes follow")
    if crc64(body) != crc:
        fail("CRC-64 of the body does not match the header")
    if version == 2:
        fail("header version 2: this checker reads version 1 bodies only")
    fields = struct.unpack(">10I", body[:40])
    npoints, nvert, svert, nlines, slines, npoly, spoly, nstrips, sstrips, nattr = fields
    off = 40
    pts = struct.unpack(f">{3 * npoints}f", body[off : off + 12 * npoints])
    off += 12 * npoints

    def cells(n, size, name):
        nonlocal off
        end = off + size
        out = []
        for _ in range(n):
            (k,) = struct.unpack(">I", body[off : off + 4])
            idx = struct.unpack(f">{k}I", body[off + 4 : off + 4 + 4 * k])
            out.append(list(idx))
            off += 4 + 4 * k
        if off != end:
            fail(f"{name}: SIZE says {size} bytes, the cells take {size - (end - off)}")
        return out

    cells(nvert, svert, "VERTICES")
    cells(nlines, slines, "LINES")
    polys = cells(npoly, spoly, "POLYGONS")
    cells(nstrips, sstrips, "TRIANGLE_STRIPS")
    headers = []
    for _ in range(nattr):
        t, n = struct.unpack(">HI", body[off : off + 6])
        headers.append((t >> 8, t & 0xFF, n))
        off += 6
    names = []
    start = off
    for _ in range(nattr):
        end = body.index(b"\0", off)
        names.append(body[off:end].decode("ascii"))
        off = end + 1
    if (off - start) % 2:
        off += 1  # padding to an even size
    attrs = {}
    for (kind, comps, n), name in zip(headers, names):
        ncomp = {0: comps, 1: 3, 2: 3, 3: 9, 4: 4}.get(kind & 0x0F)
        if ncomp is None:
            fail(f"attribute {name}: type {kind:#x}")
        vals = struct.unpack(f">{n * ncomp}f", body[off : off + 4 * n * ncomp])
        off += 4 * n * ncomp
        attrs[name] = (kind, [vals[i : i + ncomp] for i in range(0, len(vals), ncomp)])
    if off != len(body):
        fail(f"{len(body) - off} bytes after the attributes")

    if npoints != len(want["points"]):
        fail(f"NPOINTS {npoints}, expected {len(want['points'])}")
    worst = max(
        abs(pts[3 * i + a] - want["points"][i][a]) for i in range(npoints) for a in range(3)
    )
    if worst > 1e-4:
        fail(f"points differ by up to {worst} mm")
    if polys != want["triangles"]:
        fail("POLYGONS differ from the expected triangles")
    if "displacement" not in attrs or attrs["displacement"][0] != 0x01:
        fail("no point vector attribute 'displacement'")
    d = attrs["displacement"][1]
    worst_d = max(abs(d[i][a] - want["displacement"][i][a]) for i in range(npoints) for a in range(3))
    if worst_d > 1e-4:
        fail(f"displacement differs by up to {worst_d} mm")
    worst_u = 0.0
    if "uncertainty_mm" in want:
        if "uncertainty_mm" not in attrs or attrs["uncertainty_mm"][0] != 0x00:
            fail("no point scalar attribute 'uncertainty_mm'")
        b = attrs["uncertainty_mm"][1]
        if len(b) != npoints or any(len(x) != 1 for x in b):
            fail("uncertainty_mm: not one value per point")
        worst_u = max(abs(b[i][0] - want["uncertainty_mm"][i]) for i in range(npoints))
        if worst_u > 1e-4:
            fail(f"uncertainty_mm differs by up to {worst_u} mm")
    print(
        f"igtl_polydata: OK: {npoints} points (worst {worst:.2e} mm), {npoly} triangles, "
        f"attributes {names}, displacement worst {worst_d:.2e} mm, uncertainty worst {worst_u:.2e} mm"
    )


if __name__ == "__main__":
    main()
