#!/usr/bin/env python3
"""Soak test of `qemd serve` with random `kill -9` (issue 15). Python standard library only;
outside the cargo suite.

Starts `qemd serve` on 127.0.0.1:0 with a data directory of its own and drives a light, steady
load of small real scans from ../shared/data: whole and resumable (tus) uploads, jobs (tiled,
so that they checkpoint), result downloads (some by ranges) and synchronous requests. Every
--kill-min..--kill-max seconds it SIGKILLs the server and starts it again on the same data
directory. Interrupted tus uploads are resumed from the server's offset after the restart.

At the end (after --minutes) it stops killing, waits for every accepted job to finish and
checks:

* no accepted job is lost: each one the server answered 201 for exists and ends `successful`,
  or `failed` with a message; none is left `accepted` or `running`;
* every successful job's result bytes equal `qemd denoise`'s output for the same input and
  parameters (SHA-256 of the CLI's file, computed once per case before the run);
* every synchronous 200 carried those bytes too;
* every upload the server reported complete is still there with the SHA-256 of the file sent;
* the server's resident memory (VmRSS, sampled from /proc/PID/status) stays bounded: the peak
  of each server life is printed, and the run fails if any exceeds --rss-limit-mib.

Usage (from the repository root):

    python3 tests/soak/soak.py --qemd target/release/qemd --minutes 60
    nice -n 10 python3 tests/soak/soak.py --qemd /tmp/qemd --minutes 5 --kill-min 30 --kill-max 60

Prints a summary and writes it as JSON to WORK/summary.json (WORK: --work, default a new
temporary directory). Exit status 0 when every check holds.
"""

import argparse
import base64
import hashlib
import http.client
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time

TOKEN = "soak-token-0123"

# (name, file under the data directory, upload query, job params, output format or None,
#  CLI flags for the same parameters). Small real scans: a few seconds each even in a debug
#  build. The CLI tells the formats by extension.
CASES = [
    ("bunny-res4", "meshes/bun_zipper_res4.ply", "", {}, None, []),
    ("knight-off", "meshes/decimated-knight.off", "", {}, None, []),
    ("lamppost-pcd", "scans/lamppost.pcd", "", {"knn": 12}, "ply", ["--knn", "12"]),
    ("warsaw-las", "lidar/warsaw_small.las", "", {}, None, []),
    ("laz-classify", "lidar/32-1-472-150-76.laz", "", {"outliers": "classify"}, None,
     ["--outliers", "classify"]),
    ("kitti-bin", "scans/kitti_000008.bin", "?format=bin", {"knn": 10}, None,
     ["--knn", "10"]),
]
# Cases sent synchronously too (the quick ones), as query parameters.
SYNC_CASES = ["bunny-res4", "knight-off", "lamppost-pcd"]


def sha256(b):
    return hashlib.sha256(b).hexdigest()


def ext_of(path):
    name = os.path.basename(path)
    return name.split(".", 1)[1] if "." in name else ""


class Down(Exception):
    """The server did not answer (killed, restarting)."""


class Server:
    def __init__(self, qemd, work, config):
        self.qemd, self.work, self.config = qemd, work, config
        self.proc = None
        self.host, self.port = "127.0.0.1", 0
        self.lives = []  # per life: {"pid", "start", "end", "peak_rss_kib", "how"}
        self.lock = threading.Lock()
        self.restart = threading.Lock()  # held by the killer from the kill to the new start

    def start(self):
        log = open(os.path.join(self.work, "server.log"), "ab")
        env = dict(os.environ, QEMD_LISTEN="127.0.0.1:0",
                   QEMD_DATA_DIR=os.path.join(self.work, "data"), QEMD_LOG_LEVEL="info")
        self.proc = subprocess.Popen([self.qemd, "serve", "--config", self.config],
                                     stdout=subprocess.PIPE, stderr=log, env=env)
        line = self.proc.stdout.readline().decode().strip()
        prefix = "qemd: listening on http://"
        if not line.startswith(prefix):
            raise SystemExit(f"server did not start: `{line}` (see {self.work}/server.log)")
        host, port = line[len(prefix):].rsplit(":", 1)
        with self.lock:
            self.host, self.port = host, int(port)
            self.lives.append({"pid": self.proc.pid, "start": time.time(), "peak_rss_kib": 0})

    def rss_kib(self):
        try:
            with open(f"/proc/{self.proc.pid}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        return int(line.split()[1])
        except OSError:
            pass
        return 0

    def sample(self):
        rss = self.rss_kib()
        with self.lock:
            life = self.lives[-1]
            life["peak_rss_kib"] = max(life["peak_rss_kib"], rss)
        return rss

    def stop(self, sig):
        self.sample()
        self.proc.send_signal(sig)
        code = self.proc.wait(timeout=60)
        with self.lock:
            self.lives[-1].update(end=time.time(), how=signal.Signals(sig).name, code=code)

    def request(self, method, path, body=None, headers=None, timeout=120):
        with self.lock:
            host, port = self.host, self.port
        h = {"Authorization": f"Bearer {TOKEN}"}
        h.update(headers or {})
        c = http.client.HTTPConnection(host, port, timeout=timeout)
        try:
            c.request(method, path, body=body, headers=h)
            r = c.getresponse()
            return r.status, dict((k.lower(), v) for k, v in r.getheaders()), r.read()
        except (OSError, http.client.HTTPException) as e:
            raise Down(str(e)) from e
        finally:
            c.close()


class Soak:
    def __init__(self, args, server, expected, inputs):
        self.a, self.s = args, server
        self.expected, self.inputs = expected, inputs
        self.rng = random.Random(args.seed)
        self.jobs = {}      # id -> case
        self.uploads = {}   # upload id -> case (complete per the server)
        self.pending_tus = []  # [case, location, offset]
        self.counts = {}
        self.problems = []
        self.done_ok = set()  # jobs whose result was checked

    def count(self, what):
        self.counts[what] = self.counts.get(what, 0) + 1

    def problem(self, msg):
        print(f"PROBLEM: {msg}", flush=True)
        self.problems.append(msg)

    # -- operations -------------------------------------------------------------------------

    def upload_whole(self, case):
        name, rel, query = case[0], case[1], case[2]
        data = self.inputs[name]
        q = query + ("&" if query else "?") + "filename=" + os.path.basename(rel)
        st, _, body = self.s.request("POST", "/v1/uploads" + q, data,
                                     {"Content-Type": "application/octet-stream"})
        if st != 201:
            self.problem(f"whole upload of {name}: {st} {body[:200]!r}")
            return None
        uid = json.loads(body)["id"]
        self.uploads[uid] = name
        self.count("uploads_whole")
        return uid

    def upload_tus(self, case):
        name, rel, query = case[0], case[1], case[2]
        data = self.inputs[name]
        meta = "filename " + base64.b64encode(os.path.basename(rel).encode()).decode()
        if query:
            meta += ",format " + base64.b64encode(query.split("=", 1)[1].encode()).decode()
        st, h, body = self.s.request("POST", "/v1/uploads", b"", {
            "Upload-Length": str(len(data)), "Tus-Resumable": "1.0.0", "Upload-Metadata": meta})
        if st != 201:
            self.problem(f"tus creation for {name}: {st} {body[:200]!r}")
            return None
        entry = [case, h["location"], 0]
        self.pending_tus.append(entry)
        self.count("uploads_tus_started")
        return self.continue_tus(entry)

    def continue_tus(self, entry):
        """PATCHes the rest in chunks; returns the upload id when complete. Raises Down."""
        case, loc, _ = entry
        data = self.inputs[case[0]]
        st, h, _ = self.s.request("HEAD", loc, None, {"Tus-Resumable": "1.0.0"})
        if st != 200:
            self.problem(f"tus HEAD {loc} of {case[0]}: {st} (upload lost?)")
            self.pending_tus.remove(entry)
            return None
        offset = int(h["upload-offset"])
        if offset > len(data) or offset < entry[2]:
            self.problem(f"tus {loc}: offset {offset}, was {entry[2]}, length {len(data)}")
        entry[2] = offset
        chunk = max(len(data) // 4, 1)
        while True:
            piece = data[offset:offset + chunk]
            st, h, body = self.s.request("PATCH", loc, piece, {
                "Content-Type": "application/offset+octet-stream",
                "Upload-Offset": str(offset), "Tus-Resumable": "1.0.0"})
            if st != 204:
                self.problem(f"tus PATCH {loc} of {case[0]} at {offset}: {st} {body[:200]!r}")
                self.pending_tus.remove(entry)
                return None
            offset = int(h["upload-offset"])
            entry[2] = offset
            if offset >= len(data):
                break
            time.sleep(self.rng.uniform(0, 0.3))  # room for a kill mid-upload
        self.pending_tus.remove(entry)
        uid = loc.rstrip("/").rsplit("/", 1)[1]
        self.uploads[uid] = case[0]
        self.count("uploads_tus_complete")
        return uid

    def submit(self, case, uid):
        body = {"input": uid}
        if case[3]:
            body["params"] = dict(case[3])
        if case[4]:
            body["output_format"] = case[4]
        st, _, resp = self.s.request("POST", "/v1/jobs", json.dumps(body).encode(),
                                     {"Content-Type": "application/json"})
        if st == 201:
            self.jobs[json.loads(resp)["id"]] = case[0]
            self.count("jobs_accepted")
        elif st in (429, 503):
            self.count(f"jobs_refused_{st}")
        else:
            self.problem(f"job for {case[0]}: {st} {resp[:200]!r}")

    def sync(self, case):
        params = dict(case[3])
        if case[4]:
            params["output_format"] = case[4]
        q = "&".join(f"{k}={v}" for k, v in params.items())
        st, _, body = self.s.request("POST", "/v1/denoise" + ("?" + q if q else ""),
                                     self.inputs[case[0]],
                                     {"Content-Type": "application/octet-stream"})
        if st == 200:
            if sha256(body) != self.expected[case[0]]:
                self.problem(f"sync {case[0]}: bytes differ from the CLI's")
            self.count("sync_ok")
        elif st in (429, 503, 504):
            self.count(f"sync_{st}")
        else:
            self.problem(f"sync {case[0]}: {st} {body[:200]!r}")

    def download(self, jid, ranged):
        if not ranged:
            st, _, body = self.s.request("GET", f"/v1/jobs/{jid}/result")
            if st != 200:
                self.problem(f"result of {jid}: {st}")
                return None
            return body
        st, h, _ = self.s.request("HEAD", f"/v1/jobs/{jid}/result")
        if st != 200:
            self.problem(f"HEAD result of {jid}: {st}")
            return None
        size, out = int(h["content-length"]), b""
        step = max(size // 3, 1)
        while len(out) < size:
            end = min(len(out) + step, size) - 1
            st, _, body = self.s.request("GET", f"/v1/jobs/{jid}/result",
                                         headers={"Range": f"bytes={len(out)}-{end}"})
            if st != 206:
                self.problem(f"range of {jid}: {st}")
                return None
            out += body
        return out

    def check_job(self, jid, final):
        st, _, body = self.s.request("GET", f"/v1/jobs/{jid}")
        if st != 200:
            self.problem(f"job {jid} ({self.jobs[jid]}): GET answers {st}: lost")
            self.done_ok.add(jid)
            return "lost"
        v = json.loads(body)
        status = v["status"]
        if status == "successful" and jid not in self.done_ok:
            got = self.download(jid, ranged=self.rng.random() < 0.3)
            if got is not None:
                if sha256(got) != self.expected[self.jobs[jid]]:
                    self.problem(f"job {jid} ({self.jobs[jid]}): result differs from the CLI's")
                else:
                    self.count("results_equal_cli")
                    if (v.get("report") or {}).get("tiles_resumed", 0) > 0:
                        self.count("results_resumed_from_checkpoints")
                self.done_ok.add(jid)
        elif status == "failed" and jid not in self.done_ok:
            msg = v.get("message") or ""
            if not msg:
                self.problem(f"job {jid}: failed without a message")
            self.problem(f"job {jid} ({self.jobs[jid]}) failed: {msg}")
            self.done_ok.add(jid)
        elif final and status in ("accepted", "running"):
            self.problem(f"job {jid}: still {status} at the end")
        return status

    def outstanding(self):
        return [j for j in self.jobs if j not in self.done_ok]

    def step(self):
        """One random operation; Down propagates."""
        if self.pending_tus:
            self.count("tus_resumed_after_a_kill")
            self.continue_tus(self.pending_tus[0])
            return
        r = self.rng.random()
        if r < 0.35 and len(self.outstanding()) < self.a.max_outstanding:
            case = self.rng.choice(CASES)
            uid = self.upload_tus(case) if self.rng.random() < 0.5 else self.upload_whole(case)
            if uid:
                self.submit(case, uid)
        elif r < 0.45 and self.uploads:
            # Another job on an existing upload.
            uid = self.rng.choice(sorted(self.uploads))
            case = next(c for c in CASES if c[0] == self.uploads[uid])
            if len(self.outstanding()) < self.a.max_outstanding:
                self.submit(case, uid)
        elif r < 0.75:
            name = self.rng.choice(SYNC_CASES)
            self.sync(next(c for c in CASES if c[0] == name))
        else:
            for jid in self.outstanding()[:5]:
                self.check_job(jid, final=False)

    def check_uploads(self):
        for uid, name in sorted(self.uploads.items()):
            st, _, body = self.s.request("GET", f"/v1/uploads/{uid}")
            if st != 200:
                self.problem(f"upload {uid} ({name}): GET answers {st}")
                continue
            v = json.loads(body)
            if not v.get("complete") or v.get("sha256") != sha256(self.inputs[name]):
                self.problem(f"upload {uid} ({name}): complete {v.get('complete')}, "
                             f"sha256 {v.get('sha256')}")
            else:
                self.count("uploads_intact")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--qemd", default="target/release/qemd")
    p.add_argument("--data", default=os.path.join(os.path.dirname(__file__),
                                                  "../../../shared/data"))
    p.add_argument("--work", default=None)
    p.add_argument("--minutes", type=float, default=60)
    p.add_argument("--kill-min", type=float, default=120, help="seconds between kills, least")
    p.add_argument("--kill-max", type=float, default=300, help="seconds between kills, most")
    p.add_argument("--pause", type=float, default=1.0, help="mean seconds between operations")
    p.add_argument("--max-outstanding", type=int, default=6, help="unfinished jobs at most")
    p.add_argument("--rss-limit-mib", type=float, default=1024)
    p.add_argument("--drain-minutes", type=float, default=20)
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args()

    work = a.work or tempfile.mkdtemp(prefix="qemd-soak-")
    os.makedirs(work, exist_ok=True)
    qemd = os.path.abspath(a.qemd)
    print(f"soak: work directory {work}, binary {qemd}", flush=True)

    # Expected bytes: the CLI's output for each case, once.
    inputs, expected = {}, {}
    cli_dir = os.path.join(work, "cli")
    os.makedirs(cli_dir, exist_ok=True)
    for name, rel, query, params, out_fmt, flags in CASES:
        src = os.path.join(a.data, rel)
        with open(src, "rb") as f:
            inputs[name] = f.read()
        out = os.path.join(cli_dir, f"{name}.{out_fmt or ext_of(rel)}")
        t0 = time.time()
        run = subprocess.run([qemd, "denoise", src, "-o", out, "-q"] + flags,
                             capture_output=True, text=True)
        if run.returncode != 0:
            raise SystemExit(f"CLI failed on {rel}: {run.stderr}")
        with open(out, "rb") as f:
            expected[name] = sha256(f.read())
        print(f"soak: CLI {name}: {time.time() - t0:.2f} s", flush=True)

    config = os.path.join(work, "qemd.toml")
    with open(config, "w") as f:
        # Tiles of 1000 points: every job of more runs tiled and checkpoints, so kills land
        # in resumable runs.
        f.write(f'auth_tokens = "{TOKEN}:soak"\njob_concurrency = 1\nqueue_capacity = 32\n'
                'job_tile_points = 1000\nsync_concurrency = 2\nmemory_budget = "256 MiB"\n')
    server = Server(qemd, work, config)
    server.start()
    soak = Soak(a, server, expected, inputs)
    rng = random.Random(a.seed + 1)
    t_start = time.time()
    t_end = t_start + a.minutes * 60
    next_sample = 0.0
    kills = 0
    rss_series = []

    def maybe_sample():
        nonlocal next_sample
        now = time.time()
        if now >= next_sample:
            rss = server.sample()
            rss_series.append((round(now - t_start, 1), rss))
            next_sample = now + 5

    stop_killing = threading.Event()

    def killer():
        # Its own thread, so that kills land in the middle of requests (uploads, PATCHes, sync
        # bodies), not only between them.
        nonlocal kills
        while not stop_killing.wait(rng.uniform(a.kill_min, a.kill_max)):
            with server.restart:
                server.stop(signal.SIGKILL)
                kills += 1
                print(f"soak: {time.time() - t_start:7.0f} s  kill -9 #{kills} (peak RSS of that "
                      f"life {server.lives[-1]['peak_rss_kib'] / 1024:.0f} MiB, jobs "
                      f"{len(soak.jobs)}, outstanding {len(soak.outstanding())})", flush=True)
                server.start()

    kill_thread = threading.Thread(target=killer, daemon=True)
    kill_thread.start()
    while time.time() < t_end:
        maybe_sample()
        lives = len(server.lives)
        try:
            soak.step()
        except Down as e:
            with server.restart:  # waits for a restart in progress
                if len(server.lives) != lives:
                    soak.count("requests_cut_by_a_kill")
                elif server.proc.poll() is not None:
                    soak.problem(f"the server died on its own: exit {server.proc.returncode} "
                                 f"({e})")
                    server.lives[-1].update(end=time.time(), how="died",
                                            code=server.proc.returncode)
                    server.start()
                else:
                    soak.count("requests_failed_server_alive")
                    soak.problem(f"a request failed with the server up: {e}")
        time.sleep(rng.expovariate(1 / a.pause))
    stop_killing.set()
    kill_thread.join()

    # Drain: no more kills; finish interrupted uploads, wait for every job.
    print(f"soak: load over after {kills} kills; draining", flush=True)
    drain_end = time.time() + a.drain_minutes * 60
    while soak.pending_tus and time.time() < drain_end:
        soak.continue_tus(soak.pending_tus[0])
    while soak.outstanding() and time.time() < drain_end:
        maybe_sample()
        for jid in soak.outstanding():
            soak.check_job(jid, final=False)
        time.sleep(1)
    statuses = {}
    for jid in soak.jobs:
        s = soak.check_job(jid, final=True)
        statuses[s] = statuses.get(s, 0) + 1
    soak.check_uploads()
    maybe_sample()
    server.stop(signal.SIGTERM)

    peaks = [life["peak_rss_kib"] for life in server.lives]
    for i, peak in enumerate(peaks):
        if peak / 1024 > a.rss_limit_mib:
            soak.problem(f"server life {i}: peak RSS {peak / 1024:.0f} MiB over the limit")
    summary = {
        "minutes": round((time.time() - t_start) / 60, 1),
        "load_minutes": a.minutes,
        "kills": kills,
        "server_lives": len(server.lives),
        "jobs_accepted": len(soak.jobs),
        "job_statuses": statuses,
        "uploads_complete": len(soak.uploads),
        "counts": soak.counts,
        "peak_rss_mib_per_life": [round(p / 1024, 1) for p in peaks],
        "peak_rss_mib": round(max(peaks) / 1024, 1),
        "rss_samples": len(rss_series),
        "problems": soak.problems,
        "ok": not soak.problems,
    }
    with open(os.path.join(work, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    with open(os.path.join(work, "rss.csv"), "w") as f:
        f.write("seconds,vmrss_kib\n")
        f.writelines(f"{t},{r}\n" for t, r in rss_series)
    print(json.dumps(summary, indent=1))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
