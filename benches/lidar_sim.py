#!/usr/bin/env python3
"""Simulated LiDAR with exact truth: qemd against its peers per sensor (a benchmark, not a test).

Run through benches/lidar_sim.sh, which builds qemd and the CGAL/PCL drivers of benches/cpp/ and
then calls this script. Standard library only.

For every sensor of `qemd synth lidar` (spinning, mobile, airborne, terrestrial) at one seed:
  scan:    `qemd synth lidar --sensor S --seed SEED --density D -o scan.las --truth truth.ply
            --trajectory-out traj.txt`, and the same scan again as scan.xyz for the peers (the
            simulator is deterministic: same seed, same returns in the same order)
  methods: qemd default and `--method bilateral` on scan.las, qemd with `--trajectory traj.txt`
           (beam-constrained steps) when this build has the flag, CGAL jet k=24 and CGAL bilateral
           k=24 (sharpness 25, 3 iterations, normals from 18 neighbours) and PCL MLS (order 2,
           r = 4.5 × mean spacing, `--ordered`: every input point in the input's order) on
           scan.xyz
  score:   `qemd score OUT --truth truth.ply --noisy INPUT --json`: per class, the mean distance
           to the true surface, output over input (1.0 = nothing removed, lower is better)

Writes a Markdown table per sensor (methods × classes) to stdout, or to --out.
"""
import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time

SENSORS = ["spinning", "mobile", "airborne", "terrestrial"]
# Classes shown, in this order (the scorer's names); a class the scan lacks shows "–".
CLASSES = ["surfaces", "ground", "building", "car", "object", "wire", "pole", "fence",
           "high_vegetation", "low_vegetation", "all"]
JET_K = 24
BILATERAL = (24, 25.0, 3, 18)  # k, sharpness, iterations, normal k
MLS_FACTOR = 4.5


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def run(cmd):
    """Runs cmd; returns (stdout, user+system CPU seconds of the child, wall seconds)."""
    before = os.times()
    t0 = time.perf_counter()
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    after = os.times()
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()}")
    cpu = (after.children_user - before.children_user) + (after.children_system -
                                                          before.children_system)
    return p.stdout, cpu, wall


def has_flag(qemd, flag):
    out, _, _ = run([qemd, "denoise", "--help"])
    return flag in out


def sensor_rows(a, sensor, work):
    d = os.path.join(work, sensor)
    os.makedirs(d, exist_ok=True)
    scan, xyz = os.path.join(d, "scan.las"), os.path.join(d, "scan.xyz")
    truth, traj = os.path.join(d, "truth.ply"), os.path.join(d, "traj.txt")
    base = [a.qemd, "synth", "lidar", "--sensor", sensor, "--seed", str(a.seed),
            "--density", str(a.density)]
    run(base + ["-o", scan, "--truth", truth, "--trajectory-out", traj])
    run(base + ["-o", xyz])

    methods = [("qemd default", scan, lambda out: [a.qemd, "denoise", scan, "-o", out, "-q"]),
               ("qemd --method bilateral", scan,
                lambda out: [a.qemd, "denoise", scan, "-o", out, "-q", "--method", "bilateral"])]
    if has_flag(a.qemd, "--trajectory"):
        methods.append(("qemd --trajectory", scan,
                        lambda out: [a.qemd, "denoise", scan, "-o", out, "-q",
                                     "--trajectory", traj]))
    cgal = os.path.join(a.bin, "cgal_smooth")
    pcl = os.path.join(a.bin, "pcl_mls")
    if os.access(cgal, os.X_OK):
        methods.append((f"CGAL jet k={JET_K}", xyz,
                        lambda out: [cgal, "jet", xyz, out, str(JET_K)]))
        k, sharp, iters, nk = BILATERAL
        # The driver writes PREFIX_<iteration>.xyz per iteration; the last is scored.
        methods.append((f"CGAL bilateral k={k}, {iters} it", xyz,
                        lambda out: [cgal, "bilateral", xyz, out, str(k), str(sharp), str(iters),
                                     str(nk)]))
    if os.access(pcl, os.X_OK):
        methods.append((f"PCL MLS r={MLS_FACTOR:g}×spacing", xyz,
                        lambda out: [pcl, xyz, out, str(MLS_FACTOR), "2", str(a.threads),
                                     "--ordered"]))

    rows, counts = [], {}
    for name, noisy, cmd in methods:
        ext = ".las" if noisy == scan else ".xyz"
        out = os.path.join(d, "out" + ext)
        try:
            stdout, cpu, wall = run(cmd(out))
            if name.startswith("CGAL bilateral"):
                out = json.loads(stdout.strip().splitlines()[-1])["output"]
            s, _, _ = run([a.qemd, "score", out, "--truth", truth, "--noisy", noisy, "--json"])
        except (RuntimeError, ValueError, KeyError) as e:
            log(f"  {sensor:12} {name}: {e}")
            rows.append((name, None, None, None, str(e).splitlines()[0][:120]))
            continue
        score = json.loads(s)
        ratios = {r["class"]: r["dist_ratio"] for r in score["rows"]}
        log(f"  {sensor:12} {name:28} surfaces {ratios.get('surfaces', float('nan')):.3f}  "
            f"{wall:.1f} s wall, {cpu:.1f} s CPU")
        rows.append((name, ratios, wall, cpu, None))
        counts = {r["class"]: r["points"] for r in score["rows"]}
    return rows, counts


def table(sensor, rows, counts):
    present = [c for c in CLASSES if counts.get(c)]
    head = "| method | " + " | ".join(f"{c} ({counts[c]})" for c in present) + \
        " | wall s | CPU s |"
    lines = [f"### {sensor}", "", head, "|---" * (len(present) + 3) + "|"]
    for name, ratios, wall, cpu, err in rows:
        if ratios is None:
            lines.append(f"| {name} | failed: {err} |")
            continue
        cells = [f"{ratios[c]:.3f}" if c in ratios and ratios[c] is not None else "–"
                 for c in present]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {wall:.1f} | {cpu:.1f} |")
    return "\n".join(lines) + "\n"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--qemd", required=True)
    p.add_argument("--bin", required=True, help="directory of cgal_smooth and pcl_mls")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--density", type=float, default=1.0)
    p.add_argument("--sensors", default=",".join(SENSORS))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--work", help="keep the files here (default: a temporary directory)")
    p.add_argument("--command", help="how this run was started, for the table's header "
                   "(default: this script's own command line)")
    p.add_argument("--out", default="-")
    a = p.parse_args()
    if not a.command:
        a.command = " ".join(["python3"] + sys.argv)
    tmp = None
    work = a.work
    if not work:
        tmp = tempfile.TemporaryDirectory(prefix="qemd-lidar-sim.")
        work = tmp.name
    version, _, _ = run([a.qemd, "--version"])
    parts = [f"Measured {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC with "
             f"`{a.command}` ({version.strip()}, seed {a.seed}, density {a.density:g}). Each cell "
             "is the mean distance to the true surface, output over input (1.0 = nothing "
             "removed, lower is better); the column heads give each class's point count.\n"]
    for sensor in a.sensors.split(","):
        rows, counts = sensor_rows(a, sensor, work)
        parts.append(table(sensor, rows, counts))
    text = "\n".join(parts)
    if a.out == "-":
        sys.stdout.write(text)
    else:
        with open(a.out, "w") as f:
            f.write(text)
    if tmp:
        tmp.cleanup()


if __name__ == "__main__":
    main()
