"""`irdepth_jax.hostmem.keep_freed_memory`, each check in a fresh Python process (it changes malloc
for the rest of the process; tests/conftest.py sets IRDEPTH_DEFAULT_MALLOC=1 for the test processes,
which the children here drop): a 200 MB array freed and allocated again reuses its pages (almost
no page faults the second time) with it, and faults them all again without it; the environment
switch turns it off."""

import json
import os
import platform
import subprocess
import sys
import textwrap

import pytest

from irdepth_jax.hostmem import DISABLE_ENV

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
    reason="keep_freed_memory sets glibc malloc options: Linux with glibc only",
)

NBYTES = 200 * 2**20

CHILD = textwrap.dedent(f"""
    import ctypes, json, mmap, resource, sys

    # 4 KiB pages whatever the system's transparent huge page mode (PR_SET_THP_DISABLE = 41;
    # numpy also asks for huge pages on large arrays unless NUMPY_MADVISE_HUGEPAGE=0): one minor
    # fault per page touched
    thp_off = ctypes.CDLL(None, use_errno=True).prctl(41, 1, 0, 0, 0) == 0
    import numpy as np
    from irdepth_jax.hostmem import keep_freed_memory

    enabled = keep_freed_memory() if sys.argv[1] == "call" else None
    again = keep_freed_memory() if sys.argv[1] == "call" else None  # calling twice is harmless

    def faults_of_one_array():
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        a = np.ones({NBYTES}, np.uint8)  # malloc, then written through: every page touched
        assert int(a[::4096].sum()) == {NBYTES} // 4096
        del a  # free
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    first = faults_of_one_array()
    second = faults_of_one_array()
    print(json.dumps(dict(enabled=enabled, again=again, first=first, second=second,
                          pages={NBYTES} // mmap.PAGESIZE, thp_off=thp_off)))
""")


def run_child(mode, **env):
    child_env = {k: v for k, v in os.environ.items() if k != DISABLE_ENV}
    child_env.update(NUMPY_MADVISE_HUGEPAGE="0", **env)
    done = subprocess.run([sys.executable, "-c", CHILD, mode], env=child_env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["thp_off"], "prctl(PR_SET_THP_DISABLE) failed: fault counts would be per huge page"
    return result


def test_keep_freed_memory_reuses_pages():
    kept = run_child("call")
    assert kept["enabled"] is True and kept["again"] is True
    pages = kept["pages"]
    assert kept["first"] > 0.9 * pages, kept  # the first array's pages are new
    assert kept["second"] < 0.05 * pages, kept  # the second reuses them


def test_default_malloc_faults_again():
    default = run_child("skip")
    pages = default["pages"]
    # glibc maps a block this large afresh and unmaps it on free: new pages both times
    assert default["first"] > 0.9 * pages and default["second"] > 0.9 * pages, default


def test_environment_switch_turns_it_off():
    off = run_child("call", **{DISABLE_ENV: "1"})
    assert off["enabled"] is False and off["again"] is False
    assert off["second"] > 0.9 * off["pages"], off  # malloc left as it was
