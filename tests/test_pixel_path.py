"""The memory policy every service runs with (common/memory.py: release_memory_eagerly, trim_memory):
image-sized buffers are reused from frame to frame instead of being page-faulted in again, and what
a burst of big payloads leaves behind goes back to the OS at the next trim. Counted in page faults
and RSS (deterministic), not in time; the CPU it saves is measured by `ballbot-vision bench`."""
from __future__ import annotations

import json
import subprocess
import sys

PROBE = r"""
import json, os, resource, sys, threading
from common.memory import release_memory_eagerly, trim_memory

release_memory_eagerly()

def rss_mb():
    return int([l for l in open("/proc/self/status") if l.startswith("VmRSS")][0].split()[1]) / 1024

def frame(n=614_400):  # what a stage does to one 640x480 pair: payload in, two images, payload out
    payload = os.urandom(16) * (n // 16)
    left, right = bytes(payload[: n // 2]), bytes(payload[n // 2:])
    return len(bytes(bytearray(left + right)))

frame()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(100):
    frame()
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 100

base = rss_mb()
def burst():  # big garbage freed on other threads, as Zenoh's receive threads do
    for i in range(60):
        b = bytearray(os.urandom(1024) * (7 * 1024))
        del b
threads = [threading.Thread(target=burst) for _ in range(4)]
[t.start() for t in threads]; [t.join() for t in threads]
grown = rss_mb() - base
trim_memory()
print(json.dumps({"faults_per_frame": faults, "grown_mb": grown, "left_mb": rss_mb() - base}))
"""


def probe() -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_image_buffers_are_reused_and_a_burst_goes_back_to_the_os():
    r = probe()
    # A 640x480 pair is 150 pages per copy; mapped fresh each frame it would be >1000 faults.
    assert r["faults_per_frame"] < 50, r
    # What four threads' 7 MB buffers left in the heap is returned by one trim.
    assert r["left_mb"] < 20, r
