#!/usr/bin/env python3
"""The scan's own roughness per LAS class, against the noise the real-scan protocol adds.

The known-noise half of the real-scan protocol (benches/real_scans.py) takes the scan as the
clean reference. Where the reference is itself as rough as the added noise, a denoiser that
flattens a class also removes the reference's own roughness, which the protocol counts as error.
This prints, per class, the median over its points of the RMS distance of each point's 8 nearest
points (itself included) to their own plane (`√(λ0/5)`, as `structure::near_residual` computes
it) and its ratio to σ.

Usage: benches/reference_roughness.py SCAN.las|laz SIGMA
  SIGMA as `qemd noise SCAN -o noisy.las --level 0.3 --unit median-spacing --seed 0` prints it
  (`σ = 0.3 × L = SIGMA`). Needs numpy and laspy[lazrs]. Brute-force neighbours: O(n²), meant
  for scans of up to some 50 000 points.
"""
import sys

import laspy
import numpy as np

NEAR = 8
BLOCK = 500


def main():
    scan, sigma = sys.argv[1], float(sys.argv[2])
    las = laspy.read(scan)
    p = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    p -= p.mean(axis=0)
    cls = np.asarray(las.classification)
    res = np.zeros(len(p))
    for s in range(0, len(p), BLOCK):
        d = ((p[s:s + BLOCK, None, :] - p[None, :, :]) ** 2).sum(-1)
        near = np.argsort(d, axis=1, kind="stable")[:, :NEAR]
        for j, row in enumerate(near):
            q = p[row] - p[row].mean(axis=0)
            res[s + j] = np.sqrt(max(np.linalg.eigvalsh(q.T @ q)[0], 0.0) / (NEAR - 3))
    print(f"{scan}: σ = {sigma:.4g}")
    print("| class | points | reference roughness (median) | / σ |")
    print("|---|---|---|---|")
    for k in sorted(set(cls.tolist())):
        m = cls == k
        r = float(np.median(res[m]))
        print(f"| {k} | {int(m.sum()):,} | {r:.4g} | {r / sigma:.2f} |")


if __name__ == "__main__":
    main()
