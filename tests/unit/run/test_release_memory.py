"""release_memory: what a stage freed goes back to the system between the stages of `retarget run`."""

import numpy as np
import pytest

from retarget_cli.run.pipeline import release_memory


def _rss_kb() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


def test_freed_heap_memory_is_given_back():
    pytest.importorskip("ctypes")
    try:
        _rss_kb()
    except OSError:
        pytest.skip("no /proc/self/status on this system")
    # 600 arrays of 96 KB (below glibc's mmap threshold: from the heap), every other one freed: 28 MB of holes
    arrays = [np.ones(12_000) for _ in range(600)]
    del arrays[::2]
    before = _rss_kb()
    if not release_memory():
        pytest.skip("not glibc: nothing to trim")
    assert before - _rss_kb() > 10_000, (before, _rss_kb())
    assert all(a[0] == 1.0 for a in arrays)  # what is still in use is untouched
