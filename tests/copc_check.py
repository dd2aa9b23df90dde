"""Independent validation of a COPC file written by qemd (tests/io_copc.rs runs it).

usage: python3 copc_check.py OUT.copc.laz [SOURCE.las|laz]

With laspy (lazrs backend) and copclib:
  * the point count, the header bounds against the points, the info VLR;
  * every node of the hierarchy: its point count, and every point inside the node's cube;
  * a spatial query against a brute-force filter of all points;
  * copclib's own spatial-bounds validation and node count;
  * with SOURCE: the multiset of points equals the source's, attribute by attribute (PDRF 0-5
    sources compared through the LAS 1.4 field mapping).
Exits non-zero with a message on the first failure; prints "ok" otherwise.
"""

import sys

import copclib
import laspy
import numpy as np
from laspy.copc import Bounds, CopcReader, load_octree_for_query


def fail(msg):
    print("FAIL: " + msg)
    sys.exit(1)


def xyz_of(points):
    return np.stack([np.asarray(points.X), np.asarray(points.Y), np.asarray(points.Z)], axis=1)


def main():
    path = sys.argv[1]
    source = sys.argv[2] if len(sys.argv) > 2 else None
    full = laspy.read(path)  # as plain LAZ, through lazrs
    n = len(full.points)
    with CopcReader.open(path) as r:
        h = r.header
        info = r.copc_info
        if h.version.minor != 4 or h.point_format.id not in (6, 7, 8):
            fail(f"LAS {h.version} PDRF {h.point_format.id}")
        if h.point_count != n:
            fail(f"header count {h.point_count}, {n} points")
        scale, offset = np.asarray(h.scales), np.asarray(h.offsets)
        p = xyz_of(full) * scale + offset
        if not (np.allclose(p.min(axis=0), h.mins, atol=1e-9) and np.allclose(p.max(axis=0), h.maxs, atol=1e-9)):
            fail(f"header bounds {h.mins} {h.maxs}, points {p.min(axis=0)} {p.max(axis=0)}")
        center, half = np.asarray(info.center), info.halfsize
        if np.any(p < center - half - 1e-9) or np.any(p > center + half + 1e-9):
            fail("points outside the root cube")
        if abs(info.spacing - 2 * half / 128) > 1e-12 * half:
            fail(f"spacing {info.spacing} for halfsize {half}")

        # Every node: its count and its cube.
        nodes = load_octree_for_query(r.source, info, r.root_page)
        total = 0
        for node in nodes:
            pts = r._fetch_and_decompress_points_of_nodes([node])
            if len(pts) != node.point_count:
                fail(f"node {node.key}: {len(pts)} points, entry says {node.point_count}")
            q = xyz_of(pts) * scale + offset
            lo, hi = np.asarray(node.bounds.mins), np.asarray(node.bounds.maxs)
            eps = 1e-9 * max(1.0, half)
            if len(q) and (np.any(q < lo - eps) or np.any(q > hi + eps)):
                fail(f"node {node.key}: a point outside {lo} {hi}")
            total += len(pts)
        if total != n:
            fail(f"the nodes hold {total} points, the file {n}")
        levels = max(node.key.level for node in nodes) + 1

        # A spatial query: a box around the median point, 30 % of each horizontal extent wide.
        mins, maxs = p.min(axis=0), p.max(axis=0)
        med = np.median(p, axis=0)
        ext = (maxs - mins) * np.array([0.15, 0.15, 0.0])
        qlo = np.array([med[0] - ext[0], med[1] - ext[1], mins[2]])
        qhi = np.array([med[0] + ext[0], med[1] + ext[1], maxs[2]])
        got = r.query(Bounds(mins=qlo, maxs=qhi))
        g = xyz_of(got) * scale + offset
        inside = np.all((p >= qlo) & (p <= qhi), axis=1)
        want = xyz_of(full)[inside]
        gx = xyz_of(got)
        # laspy returns the points of the nodes that overlap the box: they must include every
        # point inside it, and those inside must be exactly the brute-force ones.
        gin = gx[np.all((g >= qlo) & (g <= qhi), axis=1)]
        a = np.unique(want, axis=0, return_counts=True)
        b = np.unique(gin, axis=0, return_counts=True)
        if len(want) == 0 or not (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])):
            fail(f"spatial query: {len(gin)} points in the box, brute force {len(want)}")

    c = copclib.FileReader(path)
    if not c.ValidateSpatialBounds(False):
        fail("copclib: spatial bounds invalid")
    cn = c.GetAllNodes()
    if sum(x.point_count for x in cn) != n:
        fail("copclib: node counts")

    if source is not None:
        compare(laspy.read(source), full)
    print(f"ok: {n} points, {len(nodes)} nodes, {levels} levels, query {len(want)} points")


def compare(src, out):
    if len(src.points) != len(out.points):
        fail(f"{len(src.points)} source points, {len(out.points)} in COPC")
    fs, fo = src.point_format, out.point_format
    cols = {}

    def both(name, a, b):
        cols[name] = (np.asarray(a).astype(np.float64), np.asarray(b).astype(np.float64))

    for d in ["X", "Y", "Z", "intensity", "return_number", "number_of_returns", "scan_direction_flag",
              "edge_of_flight_line", "synthetic", "key_point", "withheld", "user_data", "point_source_id"]:
        both(d, src[d], out[d])
    both("classification", src.classification, out.classification)
    if fs.id >= 6:
        both("scan_angle", src.scan_angle, out.scan_angle)
    else:
        # round(rank / 0.006) in 0.006 degree steps maps back to the rank.
        both("scan_angle", src.scan_angle_rank, np.round(np.asarray(out.scan_angle) * 0.006))
    gps = "gps_time" in fs.dimension_names
    both("gps_time", src.gps_time if gps else np.zeros(len(src.points)), out.gps_time)
    for d in ["red", "green", "blue", "nir"]:
        if d in fs.dimension_names:
            both(d, src[d], out[d])
    for d in fs.extra_dimension_names:
        both(d, src[d], out[d])
    names = sorted(cols)
    a = np.stack([cols[k][0] for k in names], axis=1)
    b = np.stack([cols[k][1] for k in names], axis=1)
    a = a[np.lexsort(a.T[::-1])]
    b = b[np.lexsort(b.T[::-1])]
    if not np.array_equal(a, b):
        bad = [names[j] for j in range(len(names)) if not np.array_equal(a[:, j], b[:, j])]
        fail(f"the points differ from the source's in {bad}")
    vs = {(v.user_id, v.record_id) for v in src.header.vlrs} - {("laszip encoded", 22204), ("copc", 1), ("copc", 10000)}
    vo = {(v.user_id, v.record_id) for v in out.header.vlrs}
    if not vs <= vo:
        fail(f"VLRs lost: {vs - vo}")


main()
