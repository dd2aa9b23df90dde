#!/usr/bin/env python3
"""Splits the known-noise protocol's planar points by the shape of their clean 16-NN list.

The protocol (docs/quality/real-scans.md) calls a point planar when the surface variation of its
clean 16-NN list is at most 0.005. On ring and scan-line data that also holds for a list that is
one ring (collinear: lambda1/lambda2 near 0), whose "clean local plane" has an arbitrary normal
across the ring. This prints, for each band of lambda1/lambda2 of the clean list, the planar
ratio (RMS distance to the clean local plane, out / noisy) of qemd's default and of a plain
projection onto the PCA plane of the noisy 16-NN, as a yardstick; and beside it the same ratio
measured to the clean *point* along the clean normal ("to point"). The plane runs through the
clean list's centroid, so on a curved patch it lies off the surface: a method that flattens
scores well on the first and badly on the second (docs/DECISIONS.md, "The planar ratio rewards
flattening").

    DIAG_DUMP=d.csv target/release/examples/scan_diag CLEAN NOISY > /dev/null
    python3 benches/planar_lists.py d.csv

Needs numpy and scipy. Points with a non-finite coordinate are left out.
"""
import sys

import numpy as np
from scipy.spatial import cKDTree


def pca(points):
    centroid = points.mean(1)
    centred = points - centroid[:, None]
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    return values, vectors[:, :, 0], centroid


def main():
    d = np.genfromtxt(sys.argv[1], delimiter=",", names=True)
    clean = np.c_[d["cx"], d["cy"], d["cz"]]
    noisy = np.c_[d["nx"], d["ny"], d["nz"]]
    out = np.c_[d["ox"], d["oy"], d["oz"]]
    keep = np.isfinite(clean).all(1) & np.isfinite(noisy).all(1) & np.isfinite(out).all(1)
    clean, noisy, out = clean[keep], noisy[keep], out[keep]
    _, lists = cKDTree(clean).query(clean, 16)
    values, normal, anchor = pca(clean[lists])
    planar = values[:, 0] / values.sum(1) <= 0.005
    shape = values[:, 1] / values[:, 2]
    _, nlists = cKDTree(noisy).query(noisy, 16)
    _, nnormal, centre = pca(noisy[nlists])
    projected = noisy - ((noisy - centre) * nnormal).sum(1)[:, None] * nnormal
    # As the protocol: the distance to the plane through the clean list's centroid.
    def ratio(x, m, at=anchor):
        e = ((x - at) * normal).sum(1)
        e_noisy = ((noisy - at) * normal).sum(1)
        return np.sqrt((e[m] ** 2).mean() / (e_noisy[m] ** 2).mean())

    def both(x, m):
        return f"{ratio(x, m):.3f} (to point {ratio(x, m, clean):.3f})"

    print(f"planar points {planar.sum()}: qemd {both(out, planar)}, "
          f"noisy-PCA projection {both(projected, planar)}")
    for lo, hi in [(0, 0.01), (0.01, 0.05), (0.05, 0.2), (0.2, 1.01)]:
        m = planar & (shape >= lo) & (shape < hi)
        if m.any():
            print(f"  lambda1/lambda2 in [{lo}, {hi}): {m.sum():7d} points "
                  f"({100 * m.sum() / planar.sum():4.1f} %)  qemd {both(out, m)}  "
                  f"projection {both(projected, m)}")


if __name__ == "__main__":
    main()
