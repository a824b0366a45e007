"""The decoded copy's files past the page cache: every byte back in order, in pieces of any size,
with O_DIRECT and without; a failed write is raised, not lost in the background thread."""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

import numpy as np
import pytest

from kinreg.io import direct_io
from kinreg.io.direct_io import ALIGN, DirectWriter, read_pieces


@pytest.mark.parametrize("direct", [True, False], ids=["O_DIRECT", "buffered"])
@pytest.mark.parametrize("size", [0, 1, ALIGN - 1, ALIGN, 3 * ALIGN + 17, 200_003])
def test_every_byte_comes_back_in_pieces_of_any_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     direct: bool, size: int) -> None:
    if not direct:
        monkeypatch.delattr(os, "O_DIRECT", raising=False)
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    path = tmp_path / "copy.bin"
    with DirectWriter(path, buffer_bytes=3 * ALIGN) as writer:  # buffers filled and handed over many times
        for a in range(0, size, 5_001):  # writes that straddle the buffers and the blocks
            writer.write(data[a:a + 5_001])
    assert writer.size == size == path.stat().st_size
    for piece_bytes in (30, ALIGN, 7 * 4_999):
        pieces = [bytes(p) for p in read_pieces(path, piece_bytes)]
        assert b"".join(pieces) == data
        assert all(len(p) == piece_bytes for p in pieces[:-1])


def test_a_piece_stays_valid_while_the_next_two_are_read(tmp_path: Path) -> None:
    data = np.arange(100_000, dtype=np.int64)
    path = tmp_path / "copy.bin"
    with DirectWriter(path) as writer:
        writer.write(data.tobytes())
    pieces = read_pieces(path, 8 * 10_007)
    held = []
    for k, piece in enumerate(pieces):
        held.append(np.frombuffer(piece, dtype=np.int64))
        if k >= 2:  # the piece taken two before is untouched
            assert np.array_equal(held[k - 2], data[(k - 2) * 10_007:(k - 1) * 10_007])


def test_a_failed_background_write_is_raised(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int, data: object) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    writer = DirectWriter(tmp_path / "copy.bin", buffer_bytes=ALIGN)
    monkeypatch.setattr(direct_io.os, "write", full)
    with pytest.raises(OSError, match="No space left"):
        writer.write(bytes(10 * ALIGN))  # the second full buffer waits for the first one's write
        writer.close()
    writer._abort()  # nothing left open


def test_a_file_that_ends_early_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "copy.bin"
    path.write_bytes(bytes(3 * ALIGN))
    monkeypatch.setattr(direct_io.os, "preadv", lambda fd, buffers, offset: 0)
    with pytest.raises(OSError, match="ends after 0 of 12,288 bytes"):
        list(read_pieces(path, ALIGN))


def test_a_file_system_that_refuses_an_aligned_direct_transfer_gets_a_buffered_one(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_write, real_preadv = os.write, os.preadv
    refused = []

    def picky(real):
        def call(fd, *args):
            if fcntl.fcntl(fd, fcntl.F_GETFL) & getattr(os, "O_DIRECT", 0):
                refused.append(real.__name__)
                raise OSError(errno.EINVAL, "Invalid argument")
            return real(fd, *args)
        return call

    monkeypatch.setattr(direct_io.os, "write", picky(real_write))
    monkeypatch.setattr(direct_io.os, "preadv", picky(real_preadv))
    data = bytes(range(256)) * 100
    path = tmp_path / "copy.bin"
    with DirectWriter(path, buffer_bytes=ALIGN) as writer:
        writer.write(data)
    assert b"".join(bytes(p) for p in read_pieces(path, 1000)) == data
    if hasattr(os, "O_DIRECT"):
        assert refused == ["write", "preadv"]  # each refused once, then buffered
