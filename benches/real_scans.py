#!/usr/bin/env python3
"""Real scans: qemd, CGAL and PCL under the real-scan protocol (`qemd harm`), outside the tests.

Run through benches/real_scans.sh, which installs CGAL/PCL, builds the C++ drivers in benches/cpp/
and qemd, then calls this script. Standard library only. Writes docs/quality/real-scans.md.

For every real scan SCAN (LAS/LAZ, KITTI .bin, PCD, PLY range scans under --data):
  clean.xyz     `qemd noise SCAN -o clean.xyz --level 0` (a plain conversion, for the peers)
  noisy.EXT     `qemd noise SCAN -o noisy.EXT --level 0.3 --unit median-spacing --seed 0`, in the
                scan's own format (iso Gaussian noise, σ = 0.3 × median nearest-neighbour spacing)
  noisy.xyz     `qemd noise noisy.EXT -o noisy.xyz --level 0` (so that every method denoises the
                very same coordinates; checked: `qemd harm noisy.EXT noisy.xyz` moves nothing)
  qemd methods  `qemd denoise IN -o OUT.EXT [flags]` on SCAN and on noisy.EXT (native format)
  peers         benches/cpp drivers on clean.xyz and on noisy.xyz; their outputs hold every input
                point in the input's order (CGAL bilateral carries each point's index through
                mst_orient_normals; PCL MLS maps its output back with getCorrespondingIndices and
                writes the input position for the points it produced nothing for)
  do no harm    `qemd harm SCAN OUT --json`: displacement / r16 (p50, p99, max) per class
  known noise   `qemd harm noisy.EXT OUT --clean SCAN --json`: per class RMS|out−clean| /
                RMS|noisy−clean|, and the planar points' RMS distance to the clean local plane,
                denoised / noisy

Results are cached in --work: a method's run is keyed by the method, its settings, the sha256 of
the program (qemd binary or C++ driver) and of its input file; a measurement by that and the
sha256 of the qemd binary (which measures). Rebuilding qemd therefore reruns the qemd methods and
remeasures everything, but reuses the peers' outputs.
"""
import argparse
import datetime
import fnmatch
import glob
import hashlib
import json
import math
import os
import re
import signal
import struct
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import compare_cgal_pcl as C  # noqa: E402  (the stated peer settings and versions())

# The scans, relative to --data; globs are expanded in sorted order.
SCANS = [
    "lidar/4_6_crop.las",
    "lidar/sample_c.las",
    "lidar/warsaw_small.las",
    "lidar/lone-star.copc.laz",
    "lidar/32-1-472-150-76.laz",
    "scans/kitti_000008.bin",
    "scans/*.pcd",
    "scans/bunny/*.ply",
]
NOISE_LEVEL = 0.3  # × median nearest-neighbour spacing
NOISE_SEED = 0

# Goals of the protocol.
HARM_P99 = 0.3
HARM_MAX = 0.6
CLASS_RATIO = 1.0
PLANAR_RATIO = 0.35


def _stated(method, pattern):
    m = re.fullmatch(pattern, C.STATED[method])
    if not m:
        raise SystemExit(f"cannot read the stated setting of {method}: {C.STATED[method]!r}")
    return m.groups()


JET_K = int(_stated("CGAL jet", r"k=(\d+)")[0])
_bk, _bit = _stated("CGAL bilateral", r"k=(\d+), (\d+) it")
BILATERAL_K, BILATERAL_ITERS = int(_bk), int(_bit)
MLS_FACTOR = float(_stated("PCL MLS", r"r=([0-9.]+)×spacing")[0])
MLS_ORDER = 2

# (key, name, kind, settings). kind "qemd": settings are flags of `qemd denoise`.
METHODS = [
    ("qemd-default", "qemd default", "qemd", []),
    ("qemd-paper", "qemd paper", "qemd", ["--paper"]),
    ("qemd-bilateral", "qemd bilateral", "qemd", ["--method", "bilateral"]),
    ("cgal-jet", "CGAL jet", "jet", [str(JET_K)]),
    ("cgal-bilateral", "CGAL bilateral", "bilateral",
     [str(BILATERAL_K), f"{C.BILATERAL_SHARPNESS:g}", str(BILATERAL_ITERS), str(C.NORMAL_K)]),
    ("pcl-mls", "PCL MLS", "mls", [f"{MLS_FACTOR:g}", str(MLS_ORDER)]),
]
PEERS = [name for _, name, kind, _ in METHODS if kind != "qemd"]
SETTING = {
    "qemd default": "no flags",
    "qemd paper": "`--paper`",
    "qemd bilateral": "`--method bilateral`",
    "CGAL jet": f"`jet_smooth_point_set`, k = {JET_K}",
    "CGAL bilateral": f"`bilateral_smooth_point_set`, k = {BILATERAL_K}, sharpness "
                      f"{C.BILATERAL_SHARPNESS:g}°, {BILATERAL_ITERS} iterations, PCA normals "
                      f"(k = {C.NORMAL_K}) oriented by `mst_orient_normals`",
    "PCL MLS": f"`MovingLeastSquares`, order {MLS_ORDER}, r = {MLS_FACTOR:g} × the input's mean "
               "nearest-neighbour distance",
}
MODES = ("harm", "noise")  # the scan as it is; the noisy scan


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def run(cmd):
    try:
        return subprocess.run(cmd, check=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    except subprocess.CalledProcessError as e:
        log(f"command failed: {' '.join(map(str, cmd))}\n{e.stderr}")
        raise


def sha256(path, cache={}):
    st = os.stat(path)
    k = (os.path.abspath(path), st.st_size, st.st_mtime_ns)
    if k not in cache:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        cache[k] = h.hexdigest()
    return cache[k]


def key_of(*parts):
    return hashlib.sha256(json.dumps(parts).encode()).hexdigest()[:24]


def native_ext(path):
    """The extension qemd writes the scan's own format with."""
    return os.path.splitext(path)[1].lower()  # .copc.laz -> .laz


def slug(scan_id):
    return re.sub(r"[^A-Za-z0-9._-]+", "_", scan_id)


def last_line(text):
    lines = [l.strip() for l in (text or "").splitlines() if l.strip()]
    return lines[-1] if lines else "no message"


def timed(cmd, timeout):
    """Runs cmd in its own process group. Returns (status, wall_s, stdout, reason)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        return "timeout", time.perf_counter() - t0, "", f"timed out (> {timeout:g} s)"
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        why = f"exit status {p.returncode}" if p.returncode > 0 else \
            f"killed by signal {-p.returncode}"
        return "failed", wall, out, f"{why}: {last_line(err)}"
    return "ok", wall, out, ""


def lzf_decompress(data, size):
    """LZF (liblzf's format, as PCD's binary_compressed uses it)."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            out += data[i:i + ctrl + 1]
            i += ctrl + 1
            continue
        length = ctrl >> 5
        if length == 7:
            length += data[i]
            i += 1
        ref = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
        i += 1
        length += 2
        if ref < 0:
            raise ValueError("LZF: reference before the start")
        if ref + length <= len(out):
            out += out[ref:ref + length]
        else:
            for j in range(length):
                out.append(out[ref + j])
    if len(out) != size:
        raise ValueError(f"LZF: {len(out)} bytes where the header says {size}")
    return bytes(out)


def pcd_to_xyz(path, out):
    """x y z of a PCD file (ascii, binary or binary_compressed; float fields), exact."""
    with open(path, "rb") as f:
        head = {}
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: no DATA line")
            w = line.decode("ascii").split()
            if not w or w[0].startswith("#"):
                continue
            head[w[0].upper()] = w[1:]
            if w[0].upper() == "DATA":
                break
        body = f.read()
    fields = head["FIELDS"]
    sizes = [int(x) for x in head["SIZE"]]
    types = head["TYPE"]
    counts = [int(x) for x in head.get("COUNT", ["1"] * len(fields))]
    n = int(head["POINTS"][0])
    fmt = {("F", 4): "f", ("F", 8): "d", ("U", 1): "B", ("U", 2): "H", ("U", 4): "I",
           ("I", 1): "b", ("I", 2): "h", ("I", 4): "i", ("U", 8): "Q", ("I", 8): "q"}
    cols = {}
    kind = head["DATA"][0]
    if kind == "ascii":
        rows = [r.split() for r in body.decode("ascii").splitlines() if r.strip()]
        at = 0
        for name, c in zip(fields, counts):
            cols[name] = [float(r[at]) for r in rows]
            at += c
    else:
        if kind == "binary_compressed":
            comp, size = struct.unpack("<II", body[:8])
            raw = lzf_decompress(body[8:8 + comp], size)
            at = 0  # field after field, each over all points
            for name, s, t, c in zip(fields, sizes, types, counts):
                vals = struct.unpack(f"<{n * c}{fmt[(t, s)]}", raw[at:at + n * s * c])
                cols[name] = vals[::c]
                at += n * s * c
        elif kind == "binary":
            rec = "<" + "".join(f"{c}{fmt[(t, s)]}" for s, t, c in zip(sizes, types, counts))
            width = struct.calcsize(rec)
            vals = list(struct.iter_unpack(rec, body[:n * width]))
            at = 0
            for name, c in zip(fields, counts):
                cols[name] = [v[at] for v in vals]
                at += c
        else:
            raise ValueError(f"{path}: DATA {kind}")
    with open(out, "w") as f:
        f.write("# x y z\n")
        for p in zip(cols["x"], cols["y"], cols["z"]):
            f.write(" ".join("NaN" if v != v else repr(float(v)) for v in p) + "\n")


def float32_exact(path):
    """Rewrites the x y z of an XYZ file as the exact values of their float32 roundings.
    Returns the largest finite |coordinate|."""
    f32 = struct.Struct("<f")
    tmp = path + ".tmp"
    big = 0.0
    with open(path) as src, open(tmp, "w") as dst:
        for line in src:
            if line.startswith("#") or not line.strip():
                dst.write(line)
                continue
            w = line.split()
            for i in range(3):
                v = float(w[i])
                if v != v or v in (float("inf"), float("-inf")):
                    continue
                x = f32.unpack(f32.pack(v))[0]
                big = max(big, abs(x))
                w[i] = repr(x)
            dst.write(" ".join(w) + "\n")
    os.replace(tmp, path)
    return big


def float32_step(x):
    """The distance between neighbouring float32 values at |x|."""
    if x == 0:
        return 0.0
    m, e = math.frexp(x)  # x = m · 2^e, 0.5 ≤ m < 1
    return math.ldexp(1.0, e - 24)


class Cache:
    def __init__(self, path, fresh):
        self.path = path
        self.data = {"runs": {}, "measures": {}, "prep": {}}
        if not fresh and os.path.exists(path):
            with open(path) as f:
                self.data.update(json.load(f))

    def save(self):
        tmp = self.path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(self.data, f, indent=1, sort_keys=True)
        os.replace(tmp, self.path)


class Bench:
    def __init__(self, a):
        self.a = a
        self.qemd = a.qemd
        self.qemd_sha = sha256(a.qemd)
        self.cgal = os.path.join(a.bin, "cgal_smooth")
        self.pcl = os.path.join(a.bin, "pcl_mls")
        self.driver_sha = {"jet": sha256(self.cgal), "bilateral": sha256(self.cgal),
                           "mls": sha256(self.pcl), "qemd": self.qemd_sha}
        os.makedirs(a.work, exist_ok=True)
        self.cache = Cache(os.path.join(a.work, "cache.json"), a.fresh)
        self.counts = {"ran": 0, "cached": 0}

    # --- the inputs of a scan ------------------------------------------------------------------
    def prepare(self, scan_id):
        scan = os.path.join(self.a.data, scan_id)
        d = os.path.join(self.a.work, slug(scan_id))
        os.makedirs(os.path.join(d, "out"), exist_ok=True)
        ext = native_ext(scan)
        files = {"scan": scan, "dir": d, "ext": ext,
                 "clean_xyz": os.path.join(d, "clean.xyz"),
                 "noisy": os.path.join(d, "noisy" + ext),
                 "noisy_xyz": os.path.join(d, "noisy.xyz")}
        k = key_of("prep", 3, sha256(scan), self.qemd_sha, NOISE_LEVEL, NOISE_SEED)
        info = self.cache.data["prep"].get(scan_id)
        needed = ("clean_xyz",) if info and info.get("noise_error") else \
            ("clean_xyz", "noisy", "noisy_xyz")
        if info and info["key"] == k and all(os.path.exists(files[f]) for f in needed):
            return files, info
        log(f"{scan_id}: preparing the noisy copy and the XYZ conversions")
        info = {"key": k, "noise_error": None, "sigma": None, "spacing": None,
                "clean_xyz_via": "qemd noise --level 0"}
        # The peers' copy of the scan. `qemd noise` refuses a cloud whose mean spacing is 0
        # (every point duplicated); the script then converts a PCD file itself.
        p = subprocess.run([self.qemd, "noise", scan, "-o", files["clean_xyz"], "--level", "0"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if p.returncode != 0:
            if ext != ".pcd":
                raise RuntimeError(f"qemd noise cannot convert {scan}: {p.stderr}")
            log(f"  qemd noise: {last_line(p.stderr)}; converting the PCD file here")
            pcd_to_xyz(scan, files["clean_xyz"])
            info["clean_xyz_via"] = "benches/real_scans.py (pcd_to_xyz)"
        with open(files["clean_xyz"]) as f:
            info["points"] = sum(1 for line in f if line.strip() and not line.startswith("#"))
        check, info["float32_step"] = self.exact_copy(scan, files["clean_xyz"])
        info.update(finite=check["count"], clean_xyz_max_move=check["absolute"]["max"],
                    clean_xyz_max_rel=check["relative"]["max"])
        p = subprocess.run([self.qemd, "noise", scan, "-o", files["noisy"], "--level",
                            str(NOISE_LEVEL), "--unit", "median-spacing", "--seed",
                            str(NOISE_SEED)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # `N points displaced with σ = LEVEL × L = SIGMA (L = SPACING)` (src/main.rs).
        m = re.search(r"(\d+) points displaced with σ = [0-9.eE+-]+ × L = ([0-9.eE+-]+) "
                      r"\(L = ([0-9.eE+-]+)\)", p.stderr)
        if p.returncode != 0 or not m:
            why = last_line(p.stderr).replace("qemd: error: ", "").replace(scan + ": ", "")
            info["noise_error"] = f"`qemd noise`: {why}"
            log(f"  no noisy copy: {info['noise_error']}")
        else:
            info["sigma"] = float(m.group(2))
            info["spacing"] = float(m.group(3))
            run([self.qemd, "noise", files["noisy"], "-o", files["noisy_xyz"], "--level", "0"])
            check, _ = self.exact_copy(files["noisy"], files["noisy_xyz"])
            info.update(noisy_xyz_max_move=check["absolute"]["max"],
                        noisy_xyz_max_rel=check["relative"]["max"])
        self.cache.data["prep"][scan_id] = info
        self.cache.save()
        return files, info

    def exact_copy(self, native, xyz):
        """Makes the XYZ copy hold exactly the coordinates qemd reads from the native file.

        qemd writes float32 coordinates (PCD, PLY, KITTI) with the shortest decimals that read
        back as the same float32; a reader of doubles gets a value up to half a float32 step
        away. Then the decimals are replaced by those of the float32 value itself. Returns the
        `all` row of `qemd harm NATIVE XYZ` (zero displacement) and the float32 step at the
        largest coordinate (None for double coordinates)."""
        def check():
            return self.all_row(json.loads(run(
                [self.qemd, "harm", native, xyz, "--json"]).stdout))
        c = check()
        if c["absolute"]["max"] == 0:
            return c, None
        big = float32_exact(xyz)
        c = check()
        if c["absolute"]["max"] != 0:
            raise RuntimeError(f"{xyz} differs from {native} by up to {c['absolute']['max']:g}")
        return c, float32_step(big)

    @staticmethod
    def all_row(harm):
        return next(r for r in harm["rows"] if r["name"] == "all")

    # --- one method on one input ---------------------------------------------------------------
    def method_run(self, files, mkey, name, kind, settings, mode):
        src = files["scan"] if mode == "harm" else files["noisy"]
        if kind != "qemd":
            src = files["clean_xyz"] if mode == "harm" else files["noisy_xyz"]
        k = key_of("run", name, kind, settings, self.driver_sha[kind], sha256(src))
        base = os.path.join(files["dir"], "out", f"{mkey}.{mode}")
        out = base + (files["ext"] if kind == "qemd" else ".xyz")
        rec = self.cache.data["runs"].get(k)
        if rec and (os.path.exists(out) if rec["status"] == "ok" else
                    rec["status"] == "failed" or rec.get("timeout", 0) >= self.a.timeout):
            self.counts["cached"] += 1
            return k, rec, out
        threads = str(os.cpu_count() or 1)
        if kind == "qemd":
            cmd = [self.qemd, "denoise", src, "-o", out, "-q"] + settings
        elif kind == "jet":
            cmd = [self.cgal, "jet", src, out] + settings
        elif kind == "bilateral":
            cmd = [self.cgal, "bilateral", src, base] + settings
        else:
            cmd = [self.pcl, src, out] + settings + [threads, "--ordered"]
        self.counts["ran"] += 1
        status, wall, stdout, reason = timed(cmd, self.a.timeout)
        rec = {"status": status, "reason": reason, "wall_s": wall, "driver": None,
               "timeout": self.a.timeout}
        if status == "ok" and kind != "qemd":
            lines = [json.loads(l) for l in stdout.splitlines() if l.strip()]
            rec["driver"] = lines[-1]
            if kind == "mls" and lines[-1].get("mls_points") == 0:
                rec["status"] = "failed"
                rec["reason"] = (f"MLS returned no point (search radius "
                                 f"{lines[-1]['radius']:g} = {MLS_FACTOR:g} × a mean spacing of "
                                 f"{lines[-1]['spacing']:g})")
            if kind == "bilateral":
                for it in range(1, BILATERAL_ITERS):
                    p = f"{base}.it{it}.xyz"
                    if os.path.exists(p):
                        os.remove(p)
                os.replace(lines[-1]["output"], out)
        if rec["status"] != "ok":
            for p in glob.glob(base + "*"):
                os.remove(p)
        self.cache.data["runs"][k] = rec
        self.cache.save()
        return k, rec, out

    def measure(self, files, run_key, out, mode):
        if mode == "harm":
            cmd = [self.qemd, "harm", files["scan"], out, "--json"]
        else:
            cmd = [self.qemd, "harm", files["noisy"], out, "--clean", files["scan"], "--json"]
        k = key_of("measure", run_key, self.qemd_sha, mode, sha256(files["scan"]))
        rec = self.cache.data["measures"].get(k)
        if rec is None:
            p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            if p.returncode == 0:
                rec = {"status": "ok", "result": json.loads(p.stdout)}
            else:
                rec = {"status": "failed", "reason": f"qemd harm: {last_line(p.stderr)}"}
            self.cache.data["measures"][k] = rec
            self.cache.save()
        return rec

    def scan(self, scan_id, methods):
        files, info = self.prepare(scan_id)
        res = {}
        for mkey, name, kind, settings in methods:
            res[name] = {}
            for mode in MODES:
                if mode == "noise" and info["noise_error"]:
                    res[name][mode] = {"status": "n/a", "wall_s": None, "driver": None,
                                       "reason": "no noisy copy: " + info["noise_error"]}
                    continue
                rk, rec, out = self.method_run(files, mkey, name, kind, settings, mode)
                cell = {"status": rec["status"], "reason": rec["reason"],
                        "wall_s": rec["wall_s"], "driver": rec["driver"]}
                if rec["status"] == "ok":
                    m = self.measure(files, rk, out, mode)
                    if m["status"] == "ok":
                        cell["result"] = m["result"]
                    else:
                        cell["status"], cell["reason"] = "failed", m["reason"]
                res[name][mode] = cell
                log(f"  {scan_id:42} {name:15} {mode:5} {cell['status']:7} "
                    f"{cell['wall_s']:8.2f} s {cell['reason']}")
        return info, res


# --- the report --------------------------------------------------------------------------------

def f2(x):
    if x is None:
        return "—"
    if x == float("inf"):
        return "inf"
    if 0 < x < 0.005:
        return f"{x:.1g}"
    return f"{x:.2f}" if x < 100 else f"{x:.0f}"


def f3(x):
    if x == float("inf"):
        return "inf"
    return f"{x:.3f}"


def pts(n):
    return f"{n:,} point" + ("s" if n != 1 else "")


def cls(row):
    """A class's name and point count."""
    return f"{row['name']}: {row['count']:,} pt" + ("s" if row["count"] != 1 else "")


def goal(x, limit):
    """x, marked when it misses the goal x ≤ limit; a third decimal where two would show the
    limit itself."""
    t = f2(x)
    if x != limit and t == f2(limit):
        t = f"{x:.3f}"
    return mark(t, x <= limit)


def mark(text, ok):
    return text if ok else f"**{text} ✗**"


def evaluate(cells):
    """Figures and goals of one method on one scan (None where a run failed)."""
    e = {"fail": {}, "na": {}}
    for mode in MODES:
        c = cells[mode]
        if c["status"] == "n/a":
            e["na"][mode] = c["reason"]
        elif c["status"] == "timeout":
            e["fail"][mode] = c["reason"]
        elif c["status"] != "ok":
            e["fail"][mode] = "failed: " + c["reason"]
    h = cells["harm"].get("result")
    if h:
        rows = h["rows"]
        classes = [r for r in rows if r["name"] != "all"] or rows
        allr = next(r for r in rows if r["name"] == "all")
        e["harm_all"] = allr["relative"]
        e["harm_p99"] = max(classes, key=lambda r: r["relative"]["p99"])
        e["harm_max"] = max(classes, key=lambda r: r["relative"]["max"])
        worst_p99 = max(r["relative"]["p99"] for r in rows)
        worst_max = max(r["relative"]["max"] for r in rows)
        e["goal_p99"] = worst_p99 <= HARM_P99
        e["goal_max"] = worst_max <= HARM_MAX
    n = cells["noise"].get("result")
    if n:
        rows = n["rows"]
        classes = [r for r in rows if r["name"] != "all"] or rows
        e["ratio_worst"] = max(classes, key=lambda r: r["ratio"])
        e["ratio_all"] = next(r for r in rows if r["name"] == "all")["ratio"]
        e["planar"] = n["planar"]
        e["goal_ratio"] = max(r["ratio"] for r in rows) <= CLASS_RATIO
        e["goal_planar"] = n["planar"]["count"] > 0 and n["planar"]["ratio"] <= PLANAR_RATIO
    return e


GOALS = [
    ("goal_p99", f"do no harm: p99 ≤ {HARM_P99:g} in every class"),
    ("goal_max", f"do no harm: max ≤ {HARM_MAX:g} in every class"),
    ("goal_ratio", f"known noise: ratio ≤ {CLASS_RATIO:g} in every class"),
    ("goal_planar", f"known noise: planar ratio ≤ {PLANAR_RATIO:g}"),
    ("goal_peers", "known noise: planar ratio below every peer's"),
]


def report(a, scans, methods, results, versions, elapsed, counts):
    names = [name for _, name, _, _ in methods]
    peers_run = [n for n in names if n in PEERS]
    ev = {s: {m: evaluate(results[s][1][m]) for m in names} for s in scans}
    # Planar ratio below every peer's that produced one.
    for s in scans:
        for m in names:
            e = ev[s][m]
            if m in PEERS or "planar" not in e or not peers_run:
                continue
            others = [ev[s][p]["planar"]["ratio"] for p in peers_run if "planar" in ev[s][p]]
            e["peers_missing"] = [p for p in peers_run if "planar" not in ev[s][p]]
            e["goal_peers"] = e["planar"]["count"] > 0 and all(
                e["planar"]["ratio"] < r for r in others)
    out = []
    w = out.append
    w("# Real scans: do no harm and known noise")
    w("")
    w(f"Generated on {a.date} by `benches/real_scans.sh` (this file is overwritten; every figure "
      "comes from the run). Regenerate with:")
    w("")
    w("```sh")
    w(a.command)
    w("```")
    w("")
    w(f"Machine: {versions['cpu']}, nproc = {versions['cores']} (wall times are indicative: "
      "the machine may be shared). Versions: " + ", ".join(
          f"{k} {v}" for k, v in versions.items() if k not in ("cpu", "cores")) + ".")
    w(f"This run took {elapsed:.0f} s: {counts['ran']} method runs done, {counts['cached']} "
      f"taken from the cache in WORK; the method runs in the tables add up to "
      f"{sum_walls(results, scans, names):.0f} s of wall time.")
    w("")
    w("## Method")
    w("")
    w(f"* **Scans**: every file below from `{a.data_label}`, as it is (LAS/LAZ, KITTI `.bin`, "
      "PCD, PLY range scans). Points with a non-finite coordinate (the organized mug scan) are "
      "carried through by every method and left out of every measure.")
    w("* **Do no harm**: each method smooths the scan as it is; "
      "`qemd harm SCAN OUT --json` gives each point's displacement over its 16-NN radius r16 in "
      "the scan (p50, p99, max), per class: the LAS classification where the file has one, "
      "otherwise the structure classes qemd finds in the scan (surface, edge, line, scatter, "
      f"sparse, …). Goal: p99 ≤ {HARM_P99:g} and max ≤ {HARM_MAX:g}, in every class.")
    w(f"* **Known noise**: noisy = scan + iso Gaussian noise, σ = {NOISE_LEVEL:g} × the scan's "
      f"median nearest-neighbour spacing, seed {NOISE_SEED} (`qemd noise SCAN -o noisy.EXT "
      f"--level {NOISE_LEVEL:g} --unit median-spacing --seed {NOISE_SEED}`, in the scan's own "
      "format, so LAS coordinates are rounded to the file's scale). `qemd harm noisy.EXT OUT "
      "--clean SCAN --json` gives per class RMS|out − scan| / RMS|noisy − scan| (goal ≤ "
      f"{CLASS_RATIO:g} in every class) and, over the planar points (surface variation of the "
      "clean 16-NN ≤ 0.005), the RMS distance to the clean local plane, out / noisy (goal ≤ "
      f"{PLANAR_RATIO:g}, and below every peer's). That plane runs through the clean list's "
      "centroid, so on a curved patch it lies off the surface and flattening scores well on it; "
      "on ring scans a list that is one ring also counts as planar. `benches/planar_lists.py` "
      "gives the same ratio measured to the clean point and split by list shape "
      "(docs/DECISIONS.md, \"The planar ratio rewards flattening\").")
    w("* **Inputs**: qemd reads and writes the scan's own format. The peers read XYZ: "
      "`qemd noise SCAN -o clean.xyz --level 0` and `qemd noise noisy.EXT -o noisy.xyz --level 0`, "
      "so every method denoises the same coordinates (checked at the end). The peers' drivers (`benches/cpp/`) write every input point, in the input's order.")
    w("* **Methods** (fixed settings, not tuned per scan; the peers' are the stated settings of "
      "`benches/compare_cgal_pcl.py`):")
    for n in names:
        w(f"  * {n}: {SETTING[n]}")
    w("  * PCL MLS drops points with fewer than 3 neighbours in its radius: such points are "
      "written at their input position (counted in the notes under each table).")
    w(f"* **Wall time**: the whole command (read, smooth, write), on the scan / on the noisy scan; "
      f"a run longer than {a.timeout:g} s is stopped and reported as timed out.")
    w("")
    w("In the tables, **bold ✗** marks a figure that misses its goal; “worst class” is the class "
      "with the highest figure (its name and point count in parentheses; small classes weigh "
      "as much as large ones).")
    w("")

    # Summary.
    w("## Summary: scans meeting each goal")
    w("")
    noise_ok = [s for s in scans if not results[s][0]["noise_error"]]
    w(f"Out of {len(scans)} scans for the do-no-harm goals and {len(noise_ok)} for the "
      "known-noise goals" + (" (no noisy copy of " + ", ".join(
          s for s in scans if s not in noise_ok) + ": see its table)" if len(noise_ok) <
          len(scans) else "") + "; a run that failed or timed out counts as missed.")
    w("")
    w("| method | " + " | ".join(g for _, g in GOALS) + " | runs failed |")
    w("|---|" + "---|" * (len(GOALS) + 1))
    for m in names:
        cells = []
        for g, _ in GOALS:
            if g == "goal_peers" and (m in PEERS or not peers_run):
                cells.append("—")
                continue
            among = scans if g in ("goal_p99", "goal_max") else noise_ok
            cells.append(f"{sum(1 for s in among if ev[s][m].get(g))}/{len(among)}")
        nfail = sum(1 for s in scans for mode in MODES if mode in ev[s][m]["fail"])
        w(f"| {m} | " + " | ".join(cells) + f" | {nfail} |")
    w("")

    # Per scan.
    w("## Per scan")
    w("")
    for s in scans:
        info, res = results[s]
        e0 = next((ev[s][m] for m in names if "harm_all" in ev[s][m]), None)
        src = None
        for m in names:
            r = res[m]["harm"].get("result")
            if r:
                src = r["classes"]
                break
        planar_n = next((ev[s][m]["planar"]["count"] for m in names if "planar" in ev[s][m]),
                        None)
        w(f"### {s}")
        w("")
        fin = info["finite"]
        line = (f"{info['points']:,} points" +
                (f" ({fin:,} finite)" if fin != info["points"] else "") +
                f"; classes: {src or '?'}; ")
        if info["noise_error"]:
            line += (f"**known noise not measured**: there is no noisy copy "
                     f"({info['noise_error']}).")
        else:
            line += (f"median spacing {info['spacing']:.4g}, σ = {info['sigma']:.4g}; planar "
                     "points: " + (f"{planar_n:,}" if planar_n is not None else "?") + ".")
            step = info.get("float32_step")
            if step and step >= 0.05 * info["sigma"]:
                line += (f" The coordinates are float32: at the largest one, neighbouring "
                         f"float32 values are {step:g} apart ({step / info['sigma']:.2g} σ), so "
                         "the noisy copy (and any float32 output) is rounded to that grid.")
        if info["clean_xyz_via"] != "qemd noise --level 0":
            line += (f" The peers' XYZ copy of the scan was written by {info['clean_xyz_via']}, "
                     "since `qemd noise --level 0` refuses the file.")
        w(line)
        w("")
        w("| method | harm p99 / max (all) | harm worst class p99 / max | noise worst class "
          "ratio | noise ratio (all) | planar ratio | wall s (scan / noisy) |")
        w("|---|---|---|---|---|---|---|")
        notes = []
        for m in names:
            e = ev[s][m]
            cells = res[m]
            row = [m]
            if "harm_all" in e:
                ha = e["harm_all"]
                row.append(f"{goal(ha['p99'], HARM_P99)} / "
                           f"{goal(ha['max'], HARM_MAX)}")
                hp, hm = e["harm_p99"], e["harm_max"]
                p99 = goal(hp["relative"]["p99"], HARM_P99)
                mx = goal(hm["relative"]["max"], HARM_MAX)
                if hp["name"] == hm["name"]:
                    row.append(f"{p99} / {mx} ({cls(hp)})")
                else:
                    row.append(f"{p99} ({cls(hp)}) / {mx} ({cls(hm)})")
            else:
                row += [f"{e['fail'].get('harm', 'no result')}", "—"]
            if "ratio_worst" in e:
                rw = e["ratio_worst"]
                row.append(f"{goal(rw['ratio'], CLASS_RATIO)} ({cls(rw)})")
                row.append(goal(e["ratio_all"], CLASS_RATIO))
                pl = e["planar"]
                if pl["count"] == 0:
                    row.append("no planar points")
                else:
                    t = goal(pl["ratio"], PLANAR_RATIO)
                    if "goal_peers" in e and not e["goal_peers"]:
                        t += " (not below every peer)"
                    row.append(t)
            elif "noise" in e["na"]:
                row += ["n/a", "n/a", "n/a"]
            else:
                row += [f"{e['fail'].get('noise', 'no result')}", "—", "—"]
            walls = []
            for mode in MODES:
                c = cells[mode]
                walls.append("timed out" if c["status"] == "timeout" else f2(c["wall_s"]))
            row.append(" / ".join(walls))
            w("| " + " | ".join(row) + " |")
            for mode in MODES:
                d = (cells[mode].get("driver") or {}) if cells[mode]["status"] == "ok" else {}
                label = "the scan as is" if mode == "harm" else "the noisy scan"
                if d.get("missing"):
                    notes.append(f"{m} on {label}: MLS produced nothing for "
                                 f"{pts(d['missing'])} (written at their input position)")
                if d.get("nonfinite_out"):
                    notes.append(f"{m} on {label}: {d['nonfinite_out']:,} non-finite "
                                 "outputs")
                if d.get("unoriented"):
                    notes.append(f"{m} on {label}: `mst_orient_normals` left "
                                 f"{pts(d['unoriented'])} unoriented (smoothed with their "
                                 "PCA normals)")
            if "harm_all" in e and e["harm_all"]["max"] == 0:
                notes.append(f"{m} moved no point of the scan as is")
            if e.get("peers_missing"):
                notes.append(f"{m}: planar ratio compared without "
                             f"{', '.join(e['peers_missing'])} (no result)")
        w("")
        for n in notes:
            w(f"* {n}")
        if notes:
            w("")

    # Per class, LAS scans.
    las = [s for s in scans if s.lower().endswith((".las", ".laz"))]
    if las and "qemd default" in names:
        w("## Per class, LAS scans")
        w("")
        w("Do no harm of qemd default per LAS class (displacement / r16), and the known-noise "
          "ratio of every method per class.")
        w("")
        for s in las:
            res = results[s][1]
            h = res["qemd default"]["harm"].get("result")
            w(f"### {s}")
            w("")
            if not h:
                w(f"qemd default: {res['qemd default']['harm']['reason'] or 'no result'}")
                w("")
                continue
            ratios = {}
            for m in names:
                n = res[m]["noise"].get("result")
                ratios[m] = {r["name"]: r["ratio"] for r in n["rows"]} if n else {}
            w("| class | points | default p50 | default p99 | default max | " +
              " | ".join(f"ratio {m}" for m in names) + " |")
            w("|---|---|---|---|---|" + "---|" * len(names))
            for r in h["rows"]:
                rel = r["relative"]
                cells = [r["name"], f"{r['count']:,}", f2(rel["p50"]),
                         goal(rel["p99"], HARM_P99),
                         goal(rel["max"], HARM_MAX)]
                for m in names:
                    x = ratios[m].get(r["name"])
                    cells.append("—" if x is None else goal(x, CLASS_RATIO))
                w("| " + " | ".join(cells) + " |")
            w("")

    w("## Checks")
    w("")
    rel = max(max(results[s][0]["clean_xyz_max_rel"], results[s][0].get("noisy_xyz_max_rel", 0))
              for s in scans)
    sig = max([max(results[s][0]["clean_xyz_max_move"], results[s][0]["noisy_xyz_max_move"])
               / results[s][0]["sigma"] for s in noise_ok] or [0])
    w("* XYZ copies for the peers (`qemd harm SCAN clean.xyz`, `qemd harm noisy.EXT noisy.xyz`): "
      f"the largest displacement over all scans is {rel:g} × r16, {sig:g} × σ. (For float32 "
      "scans the script rewrites qemd's shortest float32 decimals as the exact float32 values, "
      "which the drivers read as doubles; it stops if a copy differs from its file.)")
    fails = [(s, m, mode, ev[s][m]["fail"][mode]) for s in scans for m in names
             for mode in MODES if mode in ev[s][m]["fail"]]
    if fails:
        w("* Runs that failed or timed out:")
        for s, m, mode, why in fails:
            w(f"  * {s}, {m}, {'scan' if mode == 'harm' else 'noisy scan'}: {why}")
    else:
        w("* Every run finished and was measured.")
    w("")
    return "\n".join(out)


def sum_walls(results, scans, names):
    return sum(results[s][1][m][mode]["wall_s"] or 0 for s in scans for m in names
               for mode in MODES)


def expand_scans(data):
    ids = []
    for pat in SCANS:
        hits = sorted(glob.glob(os.path.join(data, pat)))
        if not hits:
            raise SystemExit(f"no scan matches {pat} under {data}")
        ids += [os.path.relpath(h, data) for h in hits]
    return ids


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--qemd", required=True)
    p.add_argument("--bin", required=True, help="directory of cgal_smooth and pcl_mls")
    p.add_argument("--work", required=True, help="working directory (inputs, outputs, cache)")
    p.add_argument("--data", default="../shared/data", help="directory of lidar/ and scans/")
    p.add_argument("--out", default="docs/quality/real-scans.md", help="report path, - for stdout")
    p.add_argument("--scans", nargs="+", metavar="PATTERN",
                   help="scans whose path under --data contains PATTERN or matches it as a glob")
    p.add_argument("--methods", nargs="+", metavar="METHOD",
                   help="method keys: " + ", ".join(k for k, _, _, _ in METHODS))
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per method run")
    p.add_argument("--date", default=datetime.date.today().isoformat())
    p.add_argument("--command", default="benches/real_scans.sh")
    p.add_argument("--fresh", action="store_true", help="ignore cached results in --work")
    a = p.parse_args()
    a.data_label = a.data
    scans = expand_scans(a.data)
    if a.scans:
        scans = [s for s in scans if any(pat in s or fnmatch.fnmatch(s, pat) for pat in a.scans)]
        if not scans:
            p.error("no scan matches --scans")
    methods = METHODS
    if a.methods:
        known = {k: m for m in METHODS for k in (m[0], m[1])}
        bad = [m for m in a.methods if m not in known]
        if bad:
            p.error(f"unknown methods {bad}; known: {', '.join(k for k, _, _, _ in METHODS)}")
        wanted = {known[m][0] for m in a.methods}
        methods = [m for m in METHODS if m[0] in wanted]
    t0 = time.perf_counter()
    bench = Bench(a)
    results = {}
    for s in scans:
        log(f"{s}")
        results[s] = bench.scan(s, methods)
    elapsed = time.perf_counter() - t0
    v = C.versions(a)
    try:
        dirty = run(["git", "status", "--porcelain", "--", "src", "Cargo.toml",
                     "Cargo.lock"]).stdout.strip()
        if dirty and "qemd commit" in v:
            v["qemd commit"] += " (with uncommitted changes)"
    except (subprocess.CalledProcessError, FileNotFoundError):
        pass
    text = report(a, scans, methods, results, v, elapsed, bench.counts)
    log(f"done in {elapsed:.0f} s")
    if a.out == "-":
        sys.stdout.write(text)
        return
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out, "w") as f:
        f.write(text)
    log(f"wrote {a.out}")


if __name__ == "__main__":
    main()
