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


GIVE_BACK = """
import sys
import numpy as np
from talkmesh.heap import give_back

def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024

big = np.ones(16 * 2**20, np.uint8)
del big
bufs = [np.ones(2**20, np.uint8) for _ in range(200)]
del bufs[::2]
before = rss()
if sys.argv[1] == "give-back":
    assert give_back()
print(before - rss())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc on Linux")
def test_give_back_returns_the_freed_heap():
    """The 100 MB freed inside the heap (glibc keeps it) go back to the system on give_back():
    what `talkmesh serve` does after each POST /animate job."""

    def returned(mode: str) -> float:
        out = subprocess.run(
            [sys.executable, "-c", GIVE_BACK, mode], capture_output=True, text=True
        )
        assert out.returncode == 0, out.stderr
        return float(out.stdout)

    kept, given = returned("keep"), returned("give-back")
    assert given > 90 and kept < 10, (kept, given)


def test_the_server_gives_memory_back_after_every_job(tmp_path, monkeypatch):
    """POST /animate's job ends with give_back(), also when the upload is refused."""
    import talkmesh.heap
    from talkmesh.errors import TalkmeshError
    from talkmesh.serve.files import animate_file

    calls = []
    monkeypatch.setattr(talkmesh.heap, "give_back", lambda: calls.append(1) or True)
    bad = tmp_path / "bad.wav"
    bad.write_bytes(b"RIFF not audio")
    with pytest.raises(TalkmeshError):
        animate_file(bad, tmp_path / "out.glb", "procedural")
    assert calls == [1]
