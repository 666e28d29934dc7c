"""
The host allocator's settings for CPU updates: glibc's malloc keeps freed tensor memory for the next update instead of
handing it back to the operating system.

An update allocates and frees tens of MB of activations and gradients. With glibc's default, dynamic thresholds the
larger blocks go back to the kernel on free (``munmap`` or a trim of the heap's top) and every update faults their
pages in again: the compiled ``cpu_pixels`` update (64x64 frames, one thread, AMD EPYC) took 80.7-86.6 ms with 3.7M
minor page faults and 8.7 s of system time in one timing process, and 62.3-63.8 ms with 0.45M faults and 2.6 s with
these settings. Either setting alone was slower still (95-103 ms): setting one turns off the dynamic adjustment of both.
"""

import ctypes

# mallopt's parameter numbers (glibc's malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# Blocks up to 32 MiB (the largest threshold glibc takes on a 64-bit host) come from the heap, and up to 1 GiB of freed
# memory at the heap's top stays mapped
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024


def _mallopt() -> "ctypes._CFuncPtr | None":
    """The process's own C library's ``mallopt`` (glibc's), None where it has none."""
    try:
        return ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return None


def keep_freed_memory() -> bool:
    """
    Set glibc's mmap and trim thresholds (process-wide, for every later allocation) so that freed blocks are reused.

    :return: whether both settings took effect (False off glibc)
    """
    mallopt = _mallopt()
    if mallopt is None:
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
