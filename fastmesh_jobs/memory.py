"""glibc malloc tuned for processes that must give memory back: the API's parse children and the workers."""

from __future__ import annotations

M_ARENA_MAX, M_MMAP_THRESHOLD = -8, -3  # glibc's mallopt parameters
MMAP_THRESHOLD = 256 * 1024  # bytes; larger blocks get pages of their own, returned to the system when freed


def tune_malloc(arenas: int | None = 1) -> None:
    """glibc malloc for a process that must give memory back: large blocks always in pages of their own (by
    default the threshold grows to 32 MB after the first large free, and blocks below it stay in the heap,
    fragmented, after they are freed), and ``arenas`` malloc arenas (each reserves 64 MB of address space)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)
        if arenas:
            libc.mallopt(M_ARENA_MAX, arenas)
    except (OSError, AttributeError):  # not glibc: nothing to tune
        pass


def trim_malloc() -> None:
    """Hand the memory glibc malloc holds free (in the heap and in every arena) back to the system."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to trim
        pass
