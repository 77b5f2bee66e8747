"""talkmesh.heap: a fixed malloc mmap threshold gives freed buffers back to the system, which
keeps a long `talkmesh animate` run's memory flat (docs/results/long-audio.md)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from talkmesh.heap import fix_mmap_threshold

# In a fresh process: free one 16 MB buffer (glibc then raises its mmap threshold to 16 MB),
# allocate 200 buffers of 1 MB, free every other one, and print how much of the freed 100 MB
# the process gave back.
SCRIPT = """
import sys
import numpy as np
from talkmesh.heap import fix_mmap_threshold

def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024

if sys.argv[1] == "fixed":
    assert fix_mmap_threshold()
big = np.ones(16 * 2**20, np.uint8)
del big
bufs = [np.ones(2**20, np.uint8) for _ in range(200)]
before = rss()
del bufs[::2]
print(before - rss())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc on Linux")
def test_a_fixed_mmap_threshold_gives_freed_buffers_back():
    def returned(mode: str) -> float:
        out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return float(out.stdout)

    dynamic, fixed = returned("dynamic"), returned("fixed")
    print(f"MB given back of 100 freed: glibc's default {dynamic:.0f}, fixed threshold {fixed:.0f}")
    assert fixed > 90 and dynamic < 10


def test_fixing_the_threshold_twice_is_harmless():
    first = fix_mmap_threshold()
    assert fix_mmap_threshold() == first
    assert first == sys.platform.startswith("linux")
