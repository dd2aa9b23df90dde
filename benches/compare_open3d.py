#!/usr/bin/env python3
"""Compares qemd with Open3D on the same point cloud, in one run (outside the test suite).

Open3D's `estimate_normals` with k = 16 (k-d tree k-NN + PCA) is the established neighbourhood
filter closest to qemd's point mode (k-NN + PCA + a quadric solve per point). Both run on this
machine with the same threads; CPU seconds come from getrusage, so "per core" is points per
CPU-second.

Usage: benches/compare_open3d.sh FILE.ply [QEMD_BINARY]
"""
import json
import os
import resource
import subprocess
import sys
import tempfile
import time


def cpu_seconds(who):
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def main():
    path = sys.argv[1]
    qemd = sys.argv[2] if len(sys.argv) > 2 else "target/release/qemd"
    import open3d as o3d

    w0, c0 = time.perf_counter(), cpu_seconds(resource.RUSAGE_SELF)
    pcd = o3d.io.read_point_cloud(path)
    w1, c1 = time.perf_counter(), cpu_seconds(resource.RUSAGE_SELF)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=16))
    w2, c2 = time.perf_counter(), cpu_seconds(resource.RUSAGE_SELF)
    n = len(pcd.points)
    del pcd

    def qemd_run(extra):
        with tempfile.TemporaryDirectory() as d:
            out = os.path.join(d, "out.ply")
            rep = os.path.join(d, "r.json")
            w0, c0 = time.perf_counter(), cpu_seconds(resource.RUSAGE_CHILDREN)
            subprocess.run([qemd, "denoise", path, "-o", out, "--knn", "16", "--report", rep,
                            "-q", *extra], check=True)
            w1, c1 = time.perf_counter(), cpu_seconds(resource.RUSAGE_CHILDREN)
            return w1 - w0, c1 - c0, json.load(open(rep))

    # The paper's operator (k-NN, PCA, one quadric solve) is the like-for-like comparison with
    # estimate_normals; qemd's default adds a normal filter and a second update.
    runs = [("--paper", qemd_run(["--paper"])), ("default", qemd_run([]))]

    o3d_normals_cpu = c2 - c1
    r = runs[0][1][2]
    print(f"points: {n:,}   mode: {r['mode']}   tiles: {r['tiles']}")
    print(f"{'step':52} {'wall s':>8} {'CPU s':>8} {'M pts/CPU-s':>12}")
    rows = [
        ("Open3D read_point_cloud", w1 - w0, c1 - c0),
        ("Open3D estimate_normals(knn=16)", w2 - w1, c2 - c1),
    ]
    for name, (wall, cpu, rep) in runs:
        kernel = [p for p in rep["phases"]
                  if p["name"].split(".")[-1] in ("neighbours", "normals")]
        nn_cpu = sum(p["cpu_s"] for p in kernel)
        rows.append((f"qemd denoise {name} (read, k-NN, normals, QEM, write)", wall, cpu))
        rows.append((f"qemd {name}: k-NN + normals phases only", None, nn_cpu))
    for name, wall, cpu in rows:
        ws = f"{wall:8.2f}" if wall is not None else f"{'':>8}"
        print(f"{name:52} {ws} {cpu:8.2f} {n / cpu / 1e6:12.3f}")
    print()
    for name, (wall, cpu, rep) in runs:
        print(f"qemd {name}: whole denoise per core vs Open3D normals alone = "
              f"{o3d_normals_cpu / cpu:.2f}x; wall vs Open3D read + normals = "
              f"{(w2 - w0) / wall:.2f}x")


if __name__ == "__main__":
    main()
