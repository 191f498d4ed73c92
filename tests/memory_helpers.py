"""Running kernels in a child process under an address-space limit (``ulimit -v``, as on
clusters): a buffer the limit refuses must raise ``MemoryError`` naming the argument that sets
its size. Without fallible allocation the Rust allocator aborts the process instead
("memory allocation of N bytes failed", SIGABRT), which in a child fails only the test."""

from __future__ import annotations

import subprocess
import sys

#: Defines, in the child, ``limit(extra_mib)`` (the soft limit: what the process maps now plus
#: ``extra_mib`` MiB; ``limit(None)`` lifts it) and ``attempt(what, call)``, which prints
#: ``what fitted`` or ``what MemoryError <its message>``.
PRELUDE = """
import resource

def limit(extra_mib):
    hard = resource.getrlimit(resource.RLIMIT_AS)[1]
    if extra_mib is None:
        resource.setrlimit(resource.RLIMIT_AS, (hard, hard))
        return
    with open("/proc/self/status") as f:
        used = next(int(l.split()[1]) * 1024 for l in f if l.startswith("VmSize:"))
    resource.setrlimit(resource.RLIMIT_AS, (used + (extra_mib << 20), hard))

def attempt(what, call):
    try:
        call()
        print(what, "fitted", flush=True)
    except MemoryError as e:
        print(what, "MemoryError", e, flush=True)
"""


def run_limited(code: str, timeout: float = 300.0) -> list[str]:
    """The lines ``code`` (run after :data:`PRELUDE` in a fresh interpreter) prints; asserts
    that the child ended normally (an abort is the defect these tests guard against)."""
    r = subprocess.run(
        [sys.executable, "-c", PRELUDE + code], capture_output=True, text=True, timeout=timeout
    )
    assert r.returncode == 0, f"the child ended with {r.returncode}: {r.stderr[-2000:]}"
    return r.stdout.splitlines()
