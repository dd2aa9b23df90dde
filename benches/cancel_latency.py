#!/usr/bin/env python3
"""How fast `qemd denoise` stops on SIGINT and SIGTERM, in every phase (issues 15 and 16).

    cancel_latency.py QEMD INPUT [--at SECONDS ...] [-- DENOISE FLAGS]

Starts `QEMD denoise INPUT -o <temp>.ply FLAGS` once per (time, signal), sends the signal that
many seconds after the start, and prints how long the process took to exit after it, its exit
code, its last line of stderr and whether an output file was left behind. A run that has not
exited 30 s after the signal is killed and reported. Not a test: the figures depend on the
machine; docs/RELIABILITY.md quotes them with the command.
"""
import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time


def main():
    p = argparse.ArgumentParser()
    p.add_argument("qemd")
    p.add_argument("input")
    p.add_argument("--at", type=float, nargs="+", default=[0.2, 0.5, 1, 2, 4, 8, 16])
    argv = sys.argv[1:]
    flags = argv[argv.index("--") + 1 :] if "--" in argv else []
    a = p.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    worst = 0.0
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "out.ply")
        for at in a.at:
            for sig in (signal.SIGINT, signal.SIGTERM):
                proc = subprocess.Popen(
                    [a.qemd, "denoise", a.input, "-o", out, *flags],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                )
                time.sleep(at)
                if proc.poll() is not None:
                    print(f"at {at:5.2f} s: the run had already finished")
                    break
                proc.send_signal(sig)
                sent = time.monotonic()
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                    print(f"at {at:5.2f} s {sig.name}: NOT STOPPED within 30 s")
                    worst = float("inf")
                    continue
                took = time.monotonic() - sent
                worst = max(worst, took)
                lines = proc.stderr.read().decode(errors="replace").strip().splitlines()
                print(
                    f"at {at:5.2f} s {sig.name:7}: exited {took:.3f} s later, code {proc.returncode}, "
                    f"{lines[-1] if lines else ''!r}, output left: {os.path.exists(out)}"
                )
    print(f"worst: {worst:.3f} s")


if __name__ == "__main__":
    main()
