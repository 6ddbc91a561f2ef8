"""The process's memory allocator, set for batched tensor work on the CPU.

PyTorch's CPU tensors come from the C library's malloc. glibc serves a block of 128 KiB or more
with its own ``mmap`` and returns it with ``munmap`` when freed (its threshold rises after such a
free, but trimming the heap's top gives the memory back again), so a loop that makes tensors of a
few MiB every step, as a batched environment does with its observations (B N 2n floats: 2 MiB at
B = 1024 on OFFICE), takes fresh pages from the kernel every step and faults each one in.
``keep_freed_memory`` raises both thresholds so such blocks come from the heap and are reused:
measured with ``benchmarks/bench_envs.py`` (docs/marl.md). The process
then keeps up to ``trim_mib`` of freed memory for reuse instead of returning it to the system.
"""

from __future__ import annotations

import ctypes
import functools

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h
MMAP_MAX_MIB = 32  # glibc's largest mmap threshold on 64-bit systems (HEAP_MAX_SIZE / 2)


@functools.cache
def keep_freed_memory(mmap_mib: int = MMAP_MAX_MIB, trim_mib: int = 256) -> bool:
    """Serve blocks below ``mmap_mib`` MiB from the heap and keep up to ``trim_mib`` MiB of freed
    memory there (glibc's ``mallopt``). Process-wide, once per setting; True when applied, False
    where the C library is not glibc (then nothing changes)."""
    if not 0 < mmap_mib <= MMAP_MAX_MIB or trim_mib < mmap_mib:
        raise ValueError(f"need 0 < mmap_mib <= {MMAP_MAX_MIB} and trim_mib >= mmap_mib, got {mmap_mib}, {trim_mib}")
    try:  # the process's own symbols, as shared/planners/milp.py reaches libc
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mib = 1 << 20
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_mib * mib)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_mib * mib))
