"""A data directory the server cannot write is one line and a non-zero exit, before it serves.

The check creates a file: permission bits are no test for root (os.access says yes to root for
any folder), and a read-only file system refuses root too. As root the test uses a folder of
sysfs, which refuses new files to everyone; as another user, a folder without write permission.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from greyfit.service.jobs.store import DataDirNotWritable, check_data_dir
from tests.servers import free_port

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def unwritable(tmp_path) -> Path:
    if os.geteuid() != 0:
        folder = tmp_path / "data"
        folder.mkdir()
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    sysfs = Path("/sys/kernel")
    if not sysfs.is_dir():
        pytest.skip("running as root without /sys/kernel: no folder that refuses root here")
    yield sysfs


def test_check_data_dir_tries_to_write(unwritable):
    with pytest.raises(DataDirNotWritable) as info:
        check_data_dir(unwritable)
    message = str(info.value)
    assert "\n" not in message and str(unwritable) in message and f"uid {os.geteuid()}" in message
    assert "GREYFIT_DATA_DIR" in message


def test_check_data_dir_passes_a_writable_folder_and_makes_a_missing_one(tmp_path):
    check_data_dir(tmp_path / "new" / "data", tmp_path / "new" / "data" / "greyfit.db")
    assert (tmp_path / "new" / "data").is_dir() and list((tmp_path / "new" / "data").iterdir()) == []


def test_serve_on_an_unwritable_data_dir_says_so_in_one_line(unwritable):
    proc = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "serve", "--port", str(free_port()),
                           "--data-dir", str(unwritable)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("greyfit serve: the data directory ") and "is not writable" in lines[0]
    assert "Traceback" not in proc.stderr and proc.stdout == ""
