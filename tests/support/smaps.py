"""Resident memory of one file's mappings in this process, from /proc/self/smaps (Linux)."""
from __future__ import annotations


def mapped_kb(path) -> int:
    """Resident kB of this process's mappings of ``path``."""
    kb, inside = 0, False
    for line in open("/proc/self/smaps"):
        if "-" in line.split(" ", 1)[0]:
            inside = line.rstrip().endswith(str(path))
        elif inside and line.startswith("Rss:"):
            kb += int(line.split()[1])
    return kb
