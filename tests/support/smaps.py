"""Resident memory by kind of mapping, from /proc/PID/smaps (Linux)."""
from __future__ import annotations

ARENA_ALIGN = 64 << 20  # glibc's non-main malloc arenas: heaps of HEAP_MAX_SIZE (64 MiB on 64-bit), aligned to it


def mapped_kb(path, pid: int | str = "self") -> int:
    """Resident kB of the process's mappings of ``path``."""
    kb, inside = 0, False
    for line in open(f"/proc/{pid}/smaps"):
        if "-" in line.split(" ", 1)[0]:
            inside = line.rstrip().endswith(str(path))
        elif inside and line.startswith("Rss:"):
            kb += int(line.split()[1])
    return kb


def resident_by_kind(pid: int | str = "self") -> dict[str, int]:
    """Resident kB of the process by kind: ``brk`` (glibc's main arena, [heap]), ``thread_arenas`` (anonymous
    read-write mappings at a 64 MiB boundary: the other threads' malloc arenas), ``anon`` (the other anonymous
    mappings: pymalloc's arenas, malloc's mmapped chunks (large blocks, numpy arrays), thread stacks),
    ``files`` (libraries and other files), ``total``."""
    kinds = {"brk": 0, "thread_arenas": 0, "anon": 0, "files": 0}
    kind = None
    for line in open(f"/proc/{pid}/smaps"):
        head = line.split(None, 6)
        if "-" in head[0] and len(head) >= 5 and not head[0].endswith(":"):
            start = int(head[0].split("-")[0], 16)
            name = head[5].strip() if len(head) > 5 else ""
            if name == "[heap]":
                kind = "brk"
            elif not name:
                kind = "thread_arenas" if start % ARENA_ALIGN == 0 and head[1].startswith("rw") else "anon"
            elif name.startswith("["):
                kind = "anon"  # [stack], [vvar], [vdso]
            else:
                kind = "files"
        elif line.startswith("Rss:") and kind is not None:
            kinds[kind] += int(line.split()[1])
    kinds["total"] = sum(kinds.values())
    return kinds
