#!/usr/bin/env python3
"""Bounded load test of `qemd serve` (Python standard library only).

Starts the release binary on 127.0.0.1:0 with a fresh data directory, then:

1. baseline: 20 synchronous POST /v1/denoise requests of a 120 k-point scan, one at a time, with
   nothing else running (the per-request service time);
2. load: two large jobs submitted at once (job_concurrency 2), and while they run, 200
   synchronous requests of the same scan, 8 in flight;
3. waits for the jobs, reads the server's peak RSS (VmHWM in /proc/<pid>/status), stops it
   with SIGTERM and prints the figures (and JSON with --json).

Usage (from the repository root, after `cargo build --release`):

    python3 benches/load.py [--bin target/release/qemd] [--requests 200] [--concurrency 8]
                            [--sync-points 120000] [--job-points 2000000] [--jobs 2]
                            [--query paper=true]
"""

import argparse
import http.client
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor


def percentile(values, q):
    s = sorted(values)
    if not s:
        return float("nan")
    k = (len(s) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (k - lo)


def vm_hwm_kib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    return 0


class Client:
    """One keep-alive connection per thread."""

    local = threading.local()

    def __init__(self, host, port):
        self.host, self.port = host, port

    def conn(self):
        c = getattr(self.local, "c", None)
        if c is None:
            c = http.client.HTTPConnection(self.host, self.port, timeout=600)
            self.local.c = c
        return c

    def request(self, method, path, body=None, headers=None):
        for attempt in range(2):
            c = self.conn()
            try:
                c.request(method, path, body=body, headers=headers or {})
                r = c.getresponse()
                data = r.read()
                return r.status, dict(r.getheaders()), data
            except (http.client.HTTPException, ConnectionError):
                c.close()
                self.local.c = None
                if attempt == 1:
                    raise


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--bin", default="target/release/qemd")
    ap.add_argument("--requests", type=int, default=200)
    ap.add_argument("--concurrency", type=int, default=8)
    ap.add_argument("--sync-points", type=int, default=120_000)
    ap.add_argument("--job-points", type=int, default=2_000_000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--baseline", type=int, default=20)
    ap.add_argument("--query", default="",
                    help="query string of the synchronous requests, e.g. paper=true")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()

    tmp = tempfile.mkdtemp(prefix="qemd-load-")
    scan = os.path.join(tmp, "scan.ply")
    big = os.path.join(tmp, "big.ply")
    for path, n, seed in [(scan, a.sync_points, 1), (big, a.job_points, 2)]:
        subprocess.run([a.bin, "synth", "torus", "-o", path, "--points", str(n), "--seed", str(seed)],
                       check=True, stderr=subprocess.DEVNULL)
    config = os.path.join(tmp, "qemd.toml")
    with open(config, "w") as f:
        f.write(f"job_concurrency = {a.jobs}\nsync_concurrency = {a.concurrency}\n"
                "log_level = \"warn\"\nmax_sync_size = \"64 MiB\"\n")
    env = dict(os.environ, QEMD_LISTEN="127.0.0.1:0", QEMD_DATA_DIR=os.path.join(tmp, "data"))
    server = subprocess.Popen([a.bin, "serve", "--config", config], env=env,
                              stdout=subprocess.PIPE, stderr=open(os.path.join(tmp, "server.log"), "w"),
                              text=True)
    line = server.stdout.readline().strip()
    assert line.startswith("qemd: listening on http://"), line
    host, port = line.rsplit("/", 1)[1].split(":")
    client = Client(host, int(port))
    body = open(scan, "rb").read()
    octet = {"content-type": "application/octet-stream"}
    errors = []
    sync_path = "/v1/denoise" + (f"?{a.query}" if a.query else "")

    def sync_once(_):
        t0 = time.perf_counter()
        status, headers, data = client.request("POST", sync_path, body, octet)
        dt = time.perf_counter() - t0
        if status != 200 or len(data) != len(body):
            errors.append((status, data[:200]))
        return dt, float(headers.get("x-qemd-wall-ms", "nan"))

    # 1. Baseline: one at a time, nothing else running.
    base = [sync_once(i) for i in range(a.baseline)]

    # 2. Load: large jobs plus concurrent synchronous requests.
    status, _, data = client.request("POST", "/v1/uploads", open(big, "rb").read(), octet)
    assert status == 201, data
    upload = json.loads(data)["id"]
    job_ids = []
    t_jobs = time.perf_counter()
    for _ in range(a.jobs):
        status, _, data = client.request("POST", "/v1/jobs", json.dumps({"input": upload}),
                                         {"content-type": "application/json"})
        assert status == 201, data
        job_ids.append(json.loads(data)["id"])
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=a.concurrency) as pool:
        results = list(pool.map(sync_once, range(a.requests)))
    load_wall = time.perf_counter() - t0
    # Were the jobs still busy when the synchronous phase ended (i.e. did they overlap it)?
    jobs_running_at_end = sum(
        json.loads(client.request("GET", f"/v1/jobs/{j}")[2])["status"] in ("accepted", "running")
        for j in job_ids)
    job_views = []
    for j in job_ids:
        while True:
            status, _, data = client.request("GET", f"/v1/jobs/{j}")
            v = json.loads(data)
            if v["status"] not in ("accepted", "running"):
                break
            time.sleep(0.2)
        job_views.append(v)
    jobs_wall = time.perf_counter() - t_jobs
    hwm = vm_hwm_kib(server.pid)
    server.send_signal(signal.SIGTERM)
    code = server.wait(timeout=60)

    lat = [r[0] * 1e3 for r in results]
    out = {
        "date": time.strftime("%Y-%m-%d"),
        "cpus": os.cpu_count(),
        "sync_points": a.sync_points,
        "sync_query": a.query,
        "body_bytes": len(body),
        "baseline_requests": len(base),
        "baseline_p50_ms": round(percentile([b[0] * 1e3 for b in base], 0.5), 1),
        "baseline_server_wall_p50_ms": round(percentile([b[1] for b in base], 0.5), 1),
        "requests": len(results),
        "concurrency": a.concurrency,
        "errors": len(errors),
        "p50_ms": round(percentile(lat, 0.5), 1),
        "p90_ms": round(percentile(lat, 0.9), 1),
        "p99_ms": round(percentile(lat, 0.99), 1),
        "max_ms": round(max(lat), 1),
        "mean_ms": round(statistics.mean(lat), 1),
        "sync_throughput_rps": round(len(results) / load_wall, 2),
        "jobs": len(job_ids),
        "job_points": a.job_points,
        "jobs_successful": sum(v["status"] == "successful" for v in job_views),
        "jobs_still_running_after_sync_phase": jobs_running_at_end,
        "job_wall_s": [round(v["report"]["wall_s"], 2) if v.get("report") else None for v in job_views],
        "jobs_total_wall_s": round(jobs_wall, 2),
        "peak_rss_mib": round(hwm / 1024, 1),
        "server_exit_code": code,
    }
    if a.json:
        print(json.dumps(out, indent=2))
    else:
        for k, v in out.items():
            print(f"{k:>38}: {v}")
    if errors:
        print("errors:", errors[:5], file=sys.stderr)
    return 0 if not errors and out["jobs_successful"] == len(job_ids) else 1


if __name__ == "__main__":
    sys.exit(main())
