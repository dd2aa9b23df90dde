#!/usr/bin/env python3
"""Writes the seed corpus of every fuzz target into tests/fuzz/corpus/<target>/ (issue 15).

Usage: python3 tests/fuzz/seeds.py [path/to/shared/data]   (default: ../shared/data)

Seeds are the files of ../shared/data (large ones cut to their first MAX_SEED bytes: header and
first records, which is where parsers branch) and the hostile cases of issue 15, made here by
byte edits: a huge coordinate, a far outlier, a flipped LZF byte, a LAZ layer size of 4 GiB,
point-wise LAZ with variable-size chunks, `POINTS0300`, junk PCD header lines, a PLY declaring
290 of 300 vertices. Nothing is copied into the repository: the corpus directory is ignored by
git and rebuilt by this script (from scratch each time, so it is deterministic).
"""

import os
import shutil
import struct
import sys

MAX_SEED = 64 * 1024
HERE = os.path.dirname(os.path.abspath(__file__))
CORPUS = os.path.join(HERE, "corpus")


def seed(target, name, data):
    d = os.path.join(CORPUS, target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data[:MAX_SEED])


def lines(n, extra=()):
    out = []
    x = 0x9E3779B97F4A7C15
    for _ in range(n):
        x ^= (x << 13) & 0xFFFFFFFFFFFFFFFF
        x ^= x >> 7
        x ^= (x << 17) & 0xFFFFFFFFFFFFFFFF
        u, v = (x % 3000) / 1000.0, ((x >> 20) % 3000) / 1000.0
        out.append(f"{u} {v} {0.1 * ((x >> 40) % 7)}")
    out.extend(extra)
    return ("\n".join(out) + "\n").encode()


def pcd_ascii(n, header_extra=b""):
    h = (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
         + header_extra
         + f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n".encode())
    return h + lines(n)


def pcd_binary(n):
    h = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
         f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n").encode()
    body = b"".join(struct.pack("<3f", *map(float, l.split())) for l in lines(n).decode().split("\n") if l)
    return h + body


def ply_ascii(declared, held):
    h = (f"ply\nformat ascii 1.0\nelement vertex {declared}\nproperty float x\n"
         f"property float y\nproperty float z\nend_header\n").encode()
    return h + lines(held)


def laz_layer_flip(copc):
    """The first chunk's first layer size of a PDRF 6-10 LAZ set to 4 GiB - 1."""
    data_start = struct.unpack_from("<I", copc, 96)[0]
    record_len = struct.unpack_from("<H", copc, 105)[0]
    at = data_start + 8 + record_len + 4
    b = bytearray(copc)
    b[at:at + 4] = b"\xff\xff\xff\xff"
    return bytes(b)


def laz_pointwise_variable(laz):
    """A point-wise chunked LAZ whose laszip VLR says point-wise compressor, variable chunks."""
    b = bytearray(laz)
    header_size = struct.unpack_from("<H", b, 94)[0]
    p = header_size
    for _ in range(struct.unpack_from("<I", b, 100)[0]):
        user = bytes(b[p + 2:p + 18]).rstrip(b"\0")
        length = struct.unpack_from("<H", b, p + 20)[0]
        if user == b"laszip encoded":
            d = p + 54
            b[d:d + 2] = struct.pack("<H", 1)
            b[d + 12:d + 16] = b"\xff\xff\xff\xff"
            break
        p += 54 + length
    return bytes(b)


def main():
    shared = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "..", "..", "shared", "data")
    shutil.rmtree(CORPUS, ignore_errors=True)
    by_ext = {
        ".ply": ["ply"], ".pcd": ["pcd"], ".las": ["las"], ".laz": ["las"], ".obj": ["obj"],
        ".off": ["off"], ".xyz": ["text"], ".txt": ["text"], ".pts": ["text"], ".bin": ["raw"],
    }
    found = 0
    for root, _, files in sorted(os.walk(shared)):
        for f in sorted(files):
            ext = os.path.splitext(f)[1].lower()
            if ext not in by_ext:
                continue
            with open(os.path.join(root, f), "rb") as fh:
                data = fh.read(4 << 20)
            found += 1
            for t in by_ext[ext]:
                body = data if t not in ("text", "raw") else b"\0" + data
                seed(t, f, body)
            seed("sniff", f, data)
            if ext == ".pcd":
                # The mug scan with one flipped byte in its LZF block (issue 15, item 2).
                if b"binary_compressed" in data[:2048]:
                    body = data.index(b"DATA binary_compressed\n") + 23
                    b = bytearray(data[:MAX_SEED])
                    if len(b) > body + 200:
                        b[body + 137] ^= 0x40
                    seed("pcd", "flipped-lzf-" + f, bytes(b))
                    seed("pcd_body", "compressed-" + f, b"\x02\x00\xff" + data[body:body + 8000])
            if f.endswith(".copc.laz"):
                seed("las", "layer-flip-" + f, laz_layer_flip(data[:MAX_SEED]))
            if ext == ".laz" and not f.endswith(".copc.laz"):
                seed("las", "pointwise-variable-" + f, laz_pointwise_variable(data[:MAX_SEED]))
    if found == 0:
        sys.exit(f"no seed files under {shared}")

    # Hand-made cases of issue 15.
    for t, prefix in (("text", b"\0"), ("sniff", b"")):
        seed(t, "huge-coordinate.xyz", prefix + lines(300, ["1e200 0 0"]))
        seed(t, "max-coordinate.xyz", prefix + lines(300, ["1.7976931348623157e308 0 0", "0 -1e13 0"]))
        seed(t, "far-outlier.xyz", prefix + lines(2000, ["1e9 1e9 1e9"]))
    seed("text", "count.pts", b"\x01" + b"300\n" + lines(300))
    seed("pcd", "points0300.pcd", pcd_ascii(3).replace(b"POINTS 3", b"POINTS0300"))
    seed("pcd", "junk-line.pcd", pcd_ascii(3, b"hello there\n"))
    seed("pcd", "ascii.pcd", pcd_ascii(50))
    seed("pcd", "binary.pcd", pcd_binary(50))
    seed("sniff", "binary.pcd", pcd_binary(50))
    seed("pcd_body", "ascii", b"\x00\x00\x31" + lines(50))
    seed("pcd_body", "binary", b"\x01\x00\x31" + pcd_binary(50).split(b"DATA binary\n", 1)[1])
    seed("ply", "declares-290-holds-300.ply", ply_ascii(290, 300))
    seed("ply", "small.ply", ply_ascii(30, 30))
    seed("obj", "tri.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    seed("off", "tri.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    seed("raw", "kitti.bin", b"\0" + struct.pack("<8f", 0, 0, 0, 1, 1, 0, 0, 1))
    seed("raw", "nuscenes.pcd.bin", b"\x01" + struct.pack("<10f", 0, 0, 0, 1, 0, 1, 0, 0, 1, 1))
    for t in sorted(os.listdir(CORPUS)):
        print(f"{t}: {len(os.listdir(os.path.join(CORPUS, t)))} seeds")


if __name__ == "__main__":
    main()
