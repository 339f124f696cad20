"""The system gives freed heap memory back after each keyframe (mcgs_warp.system.memory)."""

import json
import subprocess
import sys

import pytest

# Run in a fresh interpreter: the heap of the test process carries what earlier tests left in it (glibc's
# raised mmap and trim thresholds, holes), so its behaviour would depend on the test order.
FRAGMENT = r"""
import json
import numpy as np
from mcgs_warp.system.memory import release_freed_memory


def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024


if not release_freed_memory():
    print(json.dumps(None))
    raise SystemExit
block = np.ones(4 << 20, np.uint8)
del block  # a freed 4 MB block: glibc now serves 2 MB blocks from the heap
big, small = [], []
for _ in range(100):
    big.append(np.ones(2 << 20, np.uint8))  # touched: resident
    small.append(np.ones(256 << 10, np.uint8))  # stays, between the big ones
base = rss_mb()
del big
kept = rss_mb()
ran = release_freed_memory()
print(json.dumps({"base": base, "kept": kept, "after": rss_mb(), "ran": ran, "small": len(small)}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc heap, /proc")
def test_release_freed_memory_returns_a_fragmented_heap():
    """What a keyframe does to glibc's heap: once a large array was freed, arrays of its size come
    from the heap, and freed ones between arrays that stay are kept by the process. Releasing
    gives those pages back (most of the 200 MB freed), where without it they stay resident."""
    out = subprocess.run([sys.executable, "-c", FRAGMENT], check=True, capture_output=True, text=True).stdout
    r = json.loads(out.strip().splitlines()[-1])
    if r is None:
        pytest.skip("not glibc")
    assert r["ran"] and r["small"] == 100
    assert r["kept"] > r["base"] - 50, f"glibc returned the blocks by itself ({r}): this test no longer shows the heap's behaviour"
    assert r["after"] < r["kept"] - 150, f"resident {r['kept']:.0f} MB -> {r['after']:.0f} MB after release"
