"""core.files: a temporary name in the target folder, then rename (or link when exclusive)."""

from __future__ import annotations

import os

import pytest

from rtabmap_ros2.core import files


def test_a_planted_symlink_is_replaced_not_followed(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.txt").symlink_to(victim)
    files.write_text(out / "poses.txt", "ours\n")
    assert victim.read_text() == "precious"
    assert not (out / "poses.txt").is_symlink() and (out / "poses.txt").read_text() == "ours\n"
    assert sorted(p.name for p in out.iterdir()) == ["poses.txt"]   # no temporary left


def test_exclusive_never_follows_nor_overwrites(tmp_path):
    dangling = tmp_path / "backup.db"
    dangling.symlink_to(tmp_path / "elsewhere.db")
    with pytest.raises(FileExistsError):
        files.write_bytes(dangling, b"data", exclusive=True)
    assert not (tmp_path / "elsewhere.db").exists() and dangling.is_symlink()
    existing = tmp_path / "kept.db"
    existing.write_bytes(b"old")
    with pytest.raises(FileExistsError):
        with files.new_path(existing, exclusive=True) as tmp:
            tmp.write_bytes(b"new")
    assert existing.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["backup.db", "kept.db"]


def test_a_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with files.new_file(tmp_path / "a.csv") as f:
            f.write("half")
            raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []


def test_permissions_follow_the_umask(tmp_path):
    files.write_text(tmp_path / "a.txt", "x")
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o666 & ~umask
