"""md._memory: freed temporaries are reused in place, not page-faulted in afresh.

That the ``md`` command keeps it and ``import md`` does not: tests/test_process.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

# A 16 MB array written, freed, and allocated and written again: with freed memory kept
# (as the md command keeps it) its pages are still mapped; with glibc's defaults the first
# goes back to the kernel.
_TOUCH = """
import json, resource
import numpy as np
import md
kept = md.keep_freed_memory()
first = np.ones(2 * 1024 * 1024)
del first
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
second = np.ones(2 * 1024 * 1024)
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
print(json.dumps({"kept": kept, "faults": faults,
                  "pages": second.nbytes // 4096}))
"""


def _touch(**environment) -> dict:
    env = {**os.environ, **environment}
    out = subprocess.run(
        [sys.executable, "-c", _TOUCH],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_kept_freed_memory_serves_the_next_array():
    result = _touch()
    if not result["kept"]:
        pytest.skip("no glibc mallopt here: the C library decides")
    assert result["faults"] < 0.05 * result["pages"], result


def test_keeping_freed_memory_can_be_switched_off():
    assert _touch(LEAPMD_KEEP_FREED_MEMORY="0")["kept"] is False
