"""Bad input to ``detect`` and ``export`` (issue 15 case 3 and the failed export): one ``error:``
line, exit 2, and nothing left behind by ``export``."""

from __future__ import annotations

import subprocess
import sys

from cli_result import error_line

TIMEOUT_S = 300


def run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtabmap_ros2", *map(str, args)],
                          capture_output=True, text=True, timeout=TIMEOUT_S)


def test_detect_on_a_folder_of_unreadable_images_is_an_error(tmp_path):
    images = tmp_path / "images"
    images.mkdir()
    (images / "1.jpg").write_bytes(b"not a jpeg")
    (images / "2.png").write_bytes(b"")
    line = error_line(run("detect", images, "--out", tmp_path / "out", "--no-progress"))
    assert "none of the 2 image files" in line and str(images) in line


def test_failed_export_leaves_no_out_folder(tmp_path):
    bad_db = tmp_path / "map.db"
    bad_db.write_bytes(b"this is not an SQLite database" * 10)
    out = tmp_path / "export"
    error_line(run("export", bad_db, "--out", out))
    assert not out.exists()
    assert bad_db.read_bytes() == b"this is not an SQLite database" * 10
