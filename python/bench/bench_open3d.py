"""qemd.denoise against Open3D's estimate_normals(knn=16) alone, on one array, in one run.

    python python/bench/bench_open3d.py [N]     # N points, default 5_000_000

A noisy sphere of N points (seed 1). Prints the wall time of each (best of `REPEAT`) and their
ratio. Open3D estimates normals only; qemd estimates normals, filters them and moves every point,
so the ratio is what a denoised cloud costs over a normals pass.
"""

import os
import sys
import time

import numpy as np

import qemd

REPEAT = int(os.environ.get("QEMD_BENCH_REPEAT", "2"))


def sphere(n, seed=1):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (1.0 + 0.005 * rng.normal(size=(n, 1)))


def best(fn):
    times = []
    for _ in range(REPEAT):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    import open3d as o3d

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 5_000_000
    pts = sphere(n)

    def o3d_normals():
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=16))

    t_o3d = best(o3d_normals)
    t_qemd = best(lambda: qemd.denoise(pts))
    t_normals = best(lambda: qemd.normals(pts, knn=16))
    print(f"points: {n}, open3d {o3d.__version__}, qemd {qemd.__version__}")
    print(f"open3d estimate_normals(knn=16): {t_o3d:.2f} s")
    print(f"qemd.normals(knn=16):            {t_normals:.2f} s  ({t_normals / t_o3d:.2f} x open3d)")
    print(f"qemd.denoise (defaults, knn 16): {t_qemd:.2f} s  ({t_qemd / t_o3d:.2f} x open3d)")


if __name__ == "__main__":
    main()
