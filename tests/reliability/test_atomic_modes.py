"""Files written atomically get the mode a plain open() gives under the umask, not 0600."""

import os
import stat

import numpy as np
import pytest

from mcgs_warp.io import atomic_write, write_image

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX file modes")


def write_all(folder):
    with atomic_write(folder / "a.txt") as f:
        f.write("text\n")
    with atomic_write(folder / "b.bin", "wb") as f:
        f.write(b"\x00\x01")
    write_image(folder / "c.png", np.zeros((4, 5, 3), np.float32))
    return [folder / "a.txt", folder / "b.bin", folder / "c.png"]


@pytest.mark.parametrize(("umask", "expected"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_modes_follow_the_umask(tmp_path, umask, expected):
    old = os.umask(umask)
    try:
        paths = write_all(tmp_path)
        with open(tmp_path / "plain.txt", "w") as f:
            f.write("reference\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(tmp_path / "plain.txt").st_mode) == expected
    for p in paths:
        assert stat.S_IMODE(os.stat(p).st_mode) == expected, p
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_umask_is_left_unchanged(tmp_path):
    old = os.umask(0o027)
    try:
        write_all(tmp_path)
        assert os.umask(0o027) == 0o027
    finally:
        os.umask(old)


def test_atomic_write_flushes_the_rename_to_disk(tmp_path, monkeypatch):
    """After the rename the folder itself is fsynced, so a checkpoint is on disk before the
    segments it replaced are deleted (a power loss cannot leave it pointing at nothing)."""
    import os
    import stat

    synced = []
    real = os.fsync

    def spy(fd):
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        return real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    with atomic_write(tmp_path / "a.txt") as f:
        f.write("x")
    assert synced == [False, True]  # the file's data, then its folder
