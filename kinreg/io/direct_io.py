"""Large temporary files written once and read once, past the page cache (``O_DIRECT``).

The decoded copy of a cloud (:data:`kinreg.run.spill.RECORDS_FILE`, 30-38 bytes a point) is
written while the cloud is decoded and read while the corrected cloud is encoded. Through the
page cache the kernel copies every byte into pages it first has to find; on a virtual machine
that hands freed memory back to its host each such page is a fault as well. Measured on the
project's 2-core machine: 2.0-2.5 s of CPU for 600 MB buffered, 0.02 s with ``O_DIRECT``
(0.5 s of wall time the disk takes on its own), and 0.03 s of CPU to read them back
(``benchmarks/RESULTS.md``). The copy is in the decoding's way otherwise: 24 s at 235 M points.

``O_DIRECT`` wants the buffer's address, the file offset and the length in whole blocks:
the bytes are gathered in page-aligned buffers (anonymous ``mmap``) of whole blocks, the last
block padded and the file cut back to its length. Where the platform has no ``O_DIRECT`` or the
file system refuses it (tmpfs, some network file systems), the same code runs buffered.
"""

from __future__ import annotations

import errno
import mmap
import os
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

# Offsets and lengths of O_DIRECT I/O in multiples of this (the page size, a multiple of every
# disk's logical block size kinreg meets).
ALIGN = 4096


def _round_up(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def _open(path: Path, flags: int) -> int:
    """A file descriptor of ``path`` opened with ``flags`` and ``O_DIRECT`` where the file
    system takes it, else without."""
    direct = getattr(os, "O_DIRECT", 0)
    if direct:
        try:
            return os.open(path, flags | direct, 0o644)
        except OSError as e:
            if e.errno not in (errno.EINVAL, errno.EOPNOTSUPP):
                raise
    return os.open(path, flags, 0o644)


class DirectWriter:
    """A new file ``path`` that :meth:`write` appends to: the bytes are copied into one of two
    aligned buffers of ``buffer_bytes``, and a full buffer is written by a background thread
    while the other fills. :meth:`close` writes the rest; an :class:`OSError` of a write is
    raised by the next :meth:`write` or by :meth:`close`. Use as a context manager: leaving it by
    an exception closes the file without raising another error."""

    def __init__(self, path: str | Path, buffer_bytes: int = 64 << 20) -> None:
        self.name = str(path)
        self.size = 0  # bytes written so far
        self._first = bytearray()  # the file's first ALIGN bytes, for close(head=...)
        capacity = _round_up(max(buffer_bytes, ALIGN))
        self._fd = _open(Path(path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        self._buffers = [mmap.mmap(-1, capacity) for _ in range(2)]
        self._current, self._fill = 0, 0
        self._pending: Future[None] | None = None
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kinreg-direct")

    def write(self, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data).cast("B")
        if self.size < ALIGN:
            self._first += view[:ALIGN - self.size]
        while len(view):
            buffer = self._buffers[self._current]
            k = min(len(view), len(buffer) - self._fill)
            buffer[self._fill:self._fill + k] = view[:k]
            self._fill += k
            self.size += k
            view = view[k:]
            if self._fill == len(buffer):
                self._hand_over(len(buffer))

    @property
    def head(self) -> bytes:
        """The file's first bytes written so far (up to :data:`ALIGN`)."""
        return bytes(self._first)

    def _hand_over(self, length: int) -> None:
        """Write the current buffer's first ``length`` bytes (whole blocks) in the background and
        switch to the other buffer once its own write is done."""
        self._wait()
        self._pending = self._thread.submit(_write_all, self._fd, memoryview(self._buffers[self._current])[:length])
        self._current, self._fill = 1 - self._current, 0

    def _wait(self) -> None:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            pending.result()

    def close(self, head: bytes | bytearray | memoryview = b"") -> None:
        """Write what is left and close the file (its length: every byte written). ``head``, at
        most :data:`ALIGN` bytes, then replaces the file's first bytes (a header known only at the
        end): the first block is written once more. Safe to call twice."""
        if self._fd < 0:
            return
        try:
            if len(head) > min(ALIGN, self.size):
                raise ValueError(f"head of {len(head)} bytes; the file's first block has {min(ALIGN, self.size)}")
            if self._fill:
                tail = self._fill
                self._buffers[self._current][tail:_round_up(tail)] = bytes(_round_up(tail) - tail)
                self._hand_over(_round_up(tail))
            self._wait()
            if len(head):
                first = self._first
                first[:len(head)] = head
                block = mmap.mmap(-1, ALIGN)  # aligned, zero padded
                block[:len(first)] = first
                with memoryview(block) as view:
                    _write_all(self._fd, view, offset=0)
                block.close()
            os.ftruncate(self._fd, self.size)  # the last block's padding
        finally:
            self._abort()

    def _abort(self) -> None:
        self._thread.shutdown(wait=True)
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> DirectWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self._abort()


def _without_direct(fd: int) -> bool:
    """Turn ``O_DIRECT`` off on ``fd``; whether it was on (a file system may take the flag at open
    and refuse an aligned transfer all the same, with ``EINVAL``)."""
    import fcntl

    flags = fcntl.fcntl(fd, fcntl.F_GETFL)
    direct = getattr(os, "O_DIRECT", 0)
    if not flags & direct:
        return False
    fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~direct)
    return True


def _write_all(fd: int, view: memoryview, offset: int | None = None) -> None:
    """Write all of ``view`` at the file's position, or at ``offset``; a transfer the file system
    refuses with ``O_DIRECT`` (``EINVAL``) is made again without it."""
    while len(view):
        try:
            n = os.write(fd, view) if offset is None else os.pwrite(fd, view, offset)
        except OSError as e:
            if e.errno != errno.EINVAL or not _without_direct(fd):
                raise
            continue
        view = view[n:]
        if offset is not None:
            offset += n


def read_pieces(path: str | Path, piece_bytes: int, n_buffers: int = 3) -> Iterator[memoryview]:
    """The file in consecutive pieces of ``piece_bytes`` (the last one shorter), each a view
    into one of ``n_buffers`` aligned buffers taken in turn: a piece stays valid until
    ``n_buffers - 1`` more pieces have been taken, and may be changed in place."""
    size = os.stat(path).st_size
    fd = _open(Path(path), os.O_RDONLY)
    try:
        count = min(n_buffers, 1 + size // piece_bytes)  # no more buffers than pieces
        buffers = [mmap.mmap(-1, _round_up(piece_bytes) + ALIGN) for _ in range(count)]
        for k, start in enumerate(range(0, size, piece_bytes)):
            length = min(piece_bytes, size - start)
            first = start - start % ALIGN
            buffer = memoryview(buffers[k % len(buffers)])
            end = _round_up(start + length) - first  # whole blocks; short at the end of the file
            done = 0
            while done < start + length - first:
                try:
                    n = os.preadv(fd, [buffer[done:end]], first + done)
                except OSError as e:
                    if e.errno != errno.EINVAL or not _without_direct(fd):
                        raise
                    continue
                if n == 0:
                    raise OSError(errno.EIO, f"{path}: ends after {first + done:,} of {size:,} bytes")
                done += n
            yield buffer[start - first:start - first + length]
    finally:
        os.close(fd)
