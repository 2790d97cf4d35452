"""Reference of io/_pages.c in Python: fault in the whole pages of a byte range of an anonymous mmap as a
write would (madvise MADV_POPULATE_WRITE, contents unchanged), holding the GIL for each call."""
from __future__ import annotations

import errno
import mmap

MADV_POPULATE_WRITE = getattr(mmap, "MADV_POPULATE_WRITE", 23)  # Linux >= 5.14


def populate(buffer: object, offset: int, length: int) -> bool:
    """populate(buffer, offset, length) -> bool: the whole pages of bytes [offset, offset + length) of an
    mmap faulted in; False when the kernel lacks MADV_POPULATE_WRITE or the buffer is not an mmap."""
    if not isinstance(buffer, mmap.mmap):
        return False
    if offset < 0 or length < 0 or offset > len(buffer) or length > len(buffer) - offset:
        raise ValueError(f"populate: bytes [{offset}, {offset} + {length}) lie outside the buffer of "
                         f"{len(buffer)} bytes")
    page = mmap.PAGESIZE  # an anonymous mmap starts on a page: offsets in it are page offsets
    lo, hi = -(-offset // page) * page, (offset + length) // page * page
    if hi <= lo:
        return True
    try:
        buffer.madvise(MADV_POPULATE_WRITE, lo, hi - lo)
    except OSError as exc:
        if exc.errno in (errno.EINVAL, errno.ENOSYS):  # a kernel before 5.14: the first writes fault the pages in
            return False
        raise
    return True
