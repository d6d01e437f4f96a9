"""The memory policy every service runs with: freed memory goes back to the OS once a second
(glibc's malloc tuned and trimmed; nothing to do on another libc). Node applies it on entering and
trims from its stats thread."""
from __future__ import annotations

import functools


@functools.lru_cache(maxsize=1)
def _libc():
    import ctypes

    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc: nothing to tune
        return None


def release_memory_eagerly() -> None:
    """Freed memory goes back to the OS once a second (trim_memory, from the stats thread), not on
    every free. glibc by default raises its mmap threshold after the first large free and then
    serves large buffers from the heap, which it rarely returns: under a flood of big garbage a
    service grew by hundreds of MB and kept them; the once-a-second trim gives them back.

    Large buffers still come from the heap, on purpose: a buffer above the mmap threshold is mapped
    fresh and unmapped on free, so every image payload (0.3-12 MB, several per frame and stage)
    would be page-faulted in again on each frame. With a 256 KB threshold a stage that only passes
    640x480 pairs on spent 3.7 ms of CPU per pair instead of 1.7 (`ballbot-vision bench` shows it
    as kernel time). One arena: malloc_trim returns the top of the main heap only, so the buffers
    Zenoh's threads free must land there too (with an arena per thread a fuzz burst left a service
    100 MB larger)."""
    libc = _libc()
    if libc is not None:
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
        libc.mallopt(M_ARENA_MAX, 1)
        libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)  # glibc's largest; pinned, so it never moves
        libc.mallopt(M_TRIM_THRESHOLD, 128 << 20)  # no trim on each free: trim_memory does it at 1 Hz


def trim_memory() -> None:
    """Give freed heap pages back to the OS (once a second, from the stats thread)."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)
