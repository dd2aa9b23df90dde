#!/usr/bin/env python3
"""Test clouds for the k-NN cost figures in docs/BENCHMARKS.md (issues 15 and 16), written as
binary little-endian PLY with double x, y, z (so `qemd denoise` runs them in memory).

    clutter.py scene N SEED OUT.ply [--far MAX] [--far-fraction F]
        three boxes and a sphere with iso noise (sigma 0.005), five dense Gaussian clusters
        (15 % of the points, sigma 0.01-0.1), 1 % exact duplicates and F (default 0.2 %) far
        outliers 50-MAX (default 500) units from the origin, shuffled
    clutter.py scene-np N SEED OUT.ply
        the same kind of scene drawn with numpy (another random stream, not the same points):
        100 M points in about 3 GB and a minute, where the pure-Python scene needs ~15 GB
    clutter.py far IN.xyz X OUT.ply
        the text cloud IN plus one point at (X, 0, 0)
    clutter.py ply IN.xyz OUT.ply
        the text cloud IN as it is
    clutter.py cube N SEED OUT.ply
        N uniform points in a 10-unit cube (a volume, for comparison)

Pure Python (numpy only for scene-np), deterministic for a given seed.
"""
import argparse
import math
import random
import struct


def write_ply(path, pts):
    with open(path, "wb") as f:
        f.write(("ply\nformat binary_little_endian 1.0\nelement vertex %d\n"
                 "property double x\nproperty double y\nproperty double z\nend_header\n"
                 % len(pts)).encode())
        f.write(b"".join(struct.pack("<3d", *p) for p in pts))


def read_xyz(path):
    return [tuple(map(float, line.split()[:3])) for line in open(path) if line.strip()]


def scene(n, seed, far=500.0, far_fraction=0.002):
    r = random.Random(seed)
    g = r.gauss
    boxes = [((-4, -4, 0), (0, 0, 3)), ((1, -3, 0), (4, 1, 1.5)), ((-3, 1, 0), (-1, 4, 4))]
    n_far = max(1, int(n * far_fraction)) if far_fraction > 0 else 0
    n_dup = n // 100
    n_clu = n * 15 // 100
    pts = []
    for i in range(n - n_far - n_dup - n_clu):
        if i % 4 == 0:
            u = [g(0, 1) for _ in range(3)]
            s = math.sqrt(sum(x * x for x in u)) or 1.0
            p = [2.5 + 1.5 * u[0] / s, 2.5 + 1.5 * u[1] / s, 1.5 + 1.5 * u[2] / s]
        else:
            lo, hi = boxes[i % 3]
            p = [r.uniform(lo[a], hi[a]) for a in range(3)]
            a = r.randrange(3)
            p[a] = lo[a] if r.random() < 0.5 else hi[a]
        pts.append(tuple(c + g(0, 0.005) for c in p))
    centres = [((-2, -2, 3.2), 0.02), ((2.5, -1, 1.6), 0.05), ((-2, 2.5, 4.1), 0.01),
               ((0, 0, 0.5), 0.1), ((3, 3, 3), 0.03)]
    for i in range(n_clu):
        c, s = centres[i % len(centres)]
        pts.append(tuple(c[a] + g(0, s) for a in range(3)))
    for _ in range(n_dup):
        pts.append(pts[r.randrange(len(pts))])
    for _ in range(n_far):
        u = [g(0, 1) for _ in range(3)]
        s = math.sqrt(sum(x * x for x in u)) or 1.0
        d = r.uniform(50, far)
        pts.append(tuple(d * x / s for x in u))
    r.shuffle(pts)
    return pts


def scene_np(n, seed, path, far=500.0, far_fraction=0.002):
    import numpy as np
    rng = np.random.default_rng(seed)
    n_far = max(1, int(n * far_fraction)) if far_fraction > 0 else 0
    n_dup = n // 100
    n_clu = n * 15 // 100
    n_surf = n - n_far - n_dup - n_clu
    pts = np.empty((n, 3))
    surf = pts[:n_surf]
    kind = np.arange(n_surf) % 4  # 0: the sphere; 1-3: the boxes
    sph = kind == 0
    u = rng.standard_normal((int(sph.sum()), 3))
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    surf[sph] = np.array([2.5, 2.5, 1.5]) + 1.5 * u
    boxes = [((-4, -4, 0), (0, 0, 3)), ((1, -3, 0), (4, 1, 1.5)), ((-3, 1, 0), (-1, 4, 4))]
    for b, (lo, hi) in enumerate(boxes):
        m = kind == b + 1
        lo, hi = np.array(lo, float), np.array(hi, float)
        p = lo + (hi - lo) * rng.random((int(m.sum()), 3))
        axis = rng.integers(0, 3, len(p))
        side = np.where(rng.random(len(p)) < 0.5, lo[axis], hi[axis])
        p[np.arange(len(p)), axis] = side
        surf[m] = p
    surf += rng.normal(0, 0.005, surf.shape)
    centres = [((-2, -2, 3.2), 0.02), ((2.5, -1, 1.6), 0.05), ((-2, 2.5, 4.1), 0.01),
               ((0, 0, 0.5), 0.1), ((3, 3, 3), 0.03)]
    clu = pts[n_surf:n_surf + n_clu]
    which = np.arange(n_clu) % len(centres)
    for c, (centre, s) in enumerate(centres):
        m = which == c
        clu[m] = np.array(centre, float) + rng.normal(0, s, (int(m.sum()), 3))
    pts[n_surf + n_clu:n_surf + n_clu + n_dup] = pts[rng.integers(0, n_surf + n_clu, n_dup)]
    u = rng.standard_normal((n_far, 3))
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    pts[n - n_far:] = u * rng.uniform(50, far, (n_far, 1))
    pts = pts[rng.permutation(n)]
    with open(path, "wb") as f:
        f.write(("ply\nformat binary_little_endian 1.0\nelement vertex %d\n"
                 "property double x\nproperty double y\nproperty double z\nend_header\n"
                 % n).encode())
        pts.astype("<f8").tofile(f)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("scene")
    s.add_argument("n", type=int)
    s.add_argument("seed", type=int)
    s.add_argument("out")
    s.add_argument("--far", type=float, default=500.0)
    s.add_argument("--far-fraction", type=float, default=0.002)
    s = sub.add_parser("scene-np")
    s.add_argument("n", type=int)
    s.add_argument("seed", type=int)
    s.add_argument("out")
    f = sub.add_parser("far")
    f.add_argument("input")
    f.add_argument("x", type=float)
    f.add_argument("out")
    p = sub.add_parser("ply")
    p.add_argument("input")
    p.add_argument("out")
    c = sub.add_parser("cube")
    c.add_argument("n", type=int)
    c.add_argument("seed", type=int)
    c.add_argument("out")
    a = ap.parse_args()
    if a.cmd == "scene":
        write_ply(a.out, scene(a.n, a.seed, a.far, a.far_fraction))
    elif a.cmd == "scene-np":
        scene_np(a.n, a.seed, a.out)
    elif a.cmd == "far":
        write_ply(a.out, read_xyz(a.input) + [(a.x, 0.0, 0.0)])
    elif a.cmd == "ply":
        write_ply(a.out, read_xyz(a.input))
    else:
        r = random.Random(a.seed)
        write_ply(a.out, [(r.random() * 10, r.random() * 10, r.random() * 10) for _ in range(a.n)])


if __name__ == "__main__":
    main()
