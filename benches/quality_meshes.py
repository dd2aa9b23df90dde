#!/usr/bin/env python3
"""Issue 5 acceptance table: the Table I protocol on every mesh, checked against each criterion.

Runs `qemd report MESH --no-pairs` (iso noise 20/40/80 %, seeds 0-4, the faithful operator =
--paper, bilateral --iterations 3, and the default) on every mesh in ../shared/data/meshes, the
two sharp-feature originals among the pairs (block, twelve) and the generated icosphere, cube and
CSG part, then writes one Markdown page with every cell and a verdict per criterion.

Usage (repository root, after `cargo build --release`):
    python3 benches/quality_meshes.py [--bin target/release/qemd] [--out docs/quality/meshes.md]
"""
import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile

SHARED = "../shared/data/meshes"
MESHES = [
    ("icosphere", "synth sphere --resolution 6", True, False),
    ("cube", "synth cube --resolution 40", True, True),
    ("csg", "synth csg --resolution 48", True, True),
    ("bunny", f"{SHARED}/bun_zipper.ply", False, False),
    ("bunny res4", f"{SHARED}/bun_zipper_res4.ply", False, False),
    ("fandisk", f"{SHARED}/fandisk.off", True, True),
    ("armadillo", f"{SHARED}/armadillo_43k.obj", True, False),
    ("knight", f"{SHARED}/decimated-knight.off", True, False),
    ("rocker arm", f"{SHARED}/rocker_arm.off", True, False),
    ("screwdriver", f"{SHARED}/screwdriver.off", True, False),
    ("block", f"{SHARED}/pairs/l0_block_0.4_original.obj", True, True),
    ("twelve", f"{SHARED}/pairs/l0_twelve_0.5imp_original.obj", True, True),
]
METHODS = ["noisy", "faithful", "bilateral", "default"]


def run(qemd, name, source, work):
    if source.startswith("synth "):
        mesh = os.path.join(work, name.replace(" ", "_") + ".ply")
        subprocess.run([qemd, *source.split(), "-o", mesh], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    else:
        mesh = source
    out = os.path.join(work, name.replace(" ", "_"))
    subprocess.run([qemd, "report", mesh, "--out", out, "--no-pairs", "--size", "120"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t = json.load(open(os.path.join(out, "table.json")))
    cells = {}
    for row in t["rows"]:
        for c in row["cells"]:
            cells[(row["method"], c["level"])] = c["mean"]
    return t, cells


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="target/release/qemd")
    ap.add_argument("--out", default="docs/quality/meshes.md")
    a = ap.parse_args()
    lines = []
    verdicts = {k: [] for k in ["surf", "ico", "ang", "xyz20", "xyz", "dvol"]}
    with tempfile.TemporaryDirectory() as work:
        for name, source, closed_expected, sharp in MESHES:
            t, cells = run(a.bin, name, source, work)
            levels = t["levels"]
            lines.append(f"### {name} ({t['vertices']} vertices)\n")
            lines.append("| level | method | surf_std | ang_deg | std_xyz | dvol_pct |")
            lines.append("|---|---|---:|---:|---:|---:|")
            for lv in levels:
                for m in METHODS:
                    c = cells.get((m, lv))
                    if c is None:
                        continue
                    dv = "–" if c["dvol_pct"] is None else f"{c['dvol_pct']:.2f}"
                    bold = "**" if m == "default" else ""
                    lines.append(f"| {lv * 100:.0f} % | {bold}{m}{bold} | {c['surf_std']:.2f} | "
                                 f"{c['ang_deg']:.2f} | {c['std_xyz']:.2f} | {dv} |")
                d, b, f, n = (cells[(m, lv)] for m in ["default", "bilateral", "faithful", "noisy"])
                tag = f"{name} {lv * 100:.0f} %"
                verdicts["surf"].append((tag, d["surf_std"] < b["surf_std"],
                                         f"{d['surf_std']:.2f} vs {b['surf_std']:.2f}"))
                if sharp:
                    ok = d["ang_deg"] < b["ang_deg"] and d["ang_deg"] < n["ang_deg"]
                    verdicts["ang"].append((tag, ok, f"{d['ang_deg']:.2f} vs bilateral "
                                            f"{b['ang_deg']:.2f}, noisy {n['ang_deg']:.2f}"))
                if abs(lv - 0.2) < 1e-9:
                    verdicts["xyz20"].append((tag, d["std_xyz"] <= 20.0, f"{d['std_xyz']:.2f}"))
                verdicts["xyz"].append((tag, d["std_xyz"] < f["std_xyz"],
                                        f"{d['std_xyz']:.2f} vs faithful {f['std_xyz']:.2f}"))
                if d["dvol_pct"] is not None:
                    verdicts["dvol"].append((tag, abs(d["dvol_pct"]) <= 0.5,
                                             f"{d['dvol_pct']:.2f} (noisy input "
                                             f"{n['dvol_pct']:.2f})"))
            if name == "icosphere":
                goals = {0.2: 4.2, 0.4: 11.2, 0.8: 18.8}
                for lv in levels:
                    d = cells[("default", lv)]["surf_std"]
                    verdicts["ico"].append((f"icosphere {lv * 100:.0f} %", d <= goals[lv],
                                            f"{d:.2f} ≤ {goals[lv]}"))
            lines.append("")
            print(f"{name}: done", file=sys.stderr)
    head = [
        "# The default operator on every mesh (issue 5 acceptance)",
        "",
        f"Generated {datetime.date.today()} by `python3 benches/quality_meshes.py` (after "
        "`cargo build --release`; needs `../shared`). Table I protocol: iso noise σ = level × L "
        "(L = mean edge of the clean mesh), seeds 0–4 averaged; `faithful` = `--paper`, "
        "`bilateral` = `--method bilateral --iterations 3`, `default` = `qemd denoise IN -o OUT`. "
        "All errors in % of L except ang_deg (degrees).",
        "",
        "## Verdicts",
        "",
    ]
    names = {
        "surf": "surf_std below bilateral's, every mesh and level",
        "ico": "icosphere surf_std ≤ 4.2 / 11.2 / 18.8",
        "ang": "ang_deg below bilateral's and the noisy input's on sharp-feature meshes",
        "xyz20": "std_xyz ≤ the noise level (20) at 20 %",
        "xyz": "std_xyz below the faithful operator's, everywhere",
        "dvol": "|dvol_pct| ≤ 0.5 on closed meshes",
    }
    for k, title in names.items():
        v = verdicts[k]
        fails = [f"{tag}: {why}" for tag, ok, why in v if not ok]
        status = "met" if not fails else f"**missed in {len(fails)} of {len(v)} cells**"
        head.append(f"* {title}: {len(v) - len(fails)}/{len(v)} cells — {status}")
        for f in fails:
            head.append(f"  * {f}")
    head += ["", "## Every cell", ""]
    with open(a.out, "w") as f:
        f.write("\n".join(head + lines) + "\n")
    print(f"wrote {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
