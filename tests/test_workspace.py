"""The workspace's writes: atomic, and a write the machine refuses is the machine's error."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from cadio.errors import MachineError
from cadio.workspace import Workspace, atomic_path, atomic_write, write_json


def _refuse(code: int) -> object:
    def refuse(*args: object, **kwargs: object) -> None:
        raise OSError(code, os.strerror(code), str(args[0]) if args else None)
    return refuse


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EACCES, errno.EROFS, errno.EIO])
def test_a_write_the_machine_refuses_is_a_machine_error_naming_the_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, code: int) -> None:
    target = tmp_path / "captures" / "scene.mcap"
    monkeypatch.setattr(os, "open", _refuse(code))  # the temporary file cannot be made
    with pytest.raises(MachineError) as err:
        write_json(target, {"a": 1})
    assert err.value.path == str(target) and os.strerror(code) in err.value.reason
    assert not isinstance(err.value, OSError)  # no stage's `except OSError` takes it for a row


def test_a_disk_filling_up_mid_write_leaves_no_file(tmp_path: Path) -> None:
    target = tmp_path / "inputs" / "points.npz"
    with pytest.raises(MachineError, match="No space left on device"), \
            atomic_write(target) as fh:
        fh.write(b"half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert list(target.parent.iterdir()) == []
    with pytest.raises(MachineError, match="Permission denied"), atomic_path(target):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))


def test_an_error_of_the_input_stays_what_it_is(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError), atomic_write(tmp_path / "out.json"):
        raise FileNotFoundError(errno.ENOENT, "the input is gone")


def test_a_folder_at_runs_latest_leaves_no_stray_link(tmp_path: Path) -> None:
    ws = Workspace(tmp_path)
    (ws.latest / "notes").mkdir(parents=True)
    ws.run_dir("20261128T000000000000Z").mkdir()
    with pytest.raises(OSError):
        ws.mark_latest("20261128T000000000000Z")
    assert sorted(p.name for p in ws.latest.parent.iterdir()) == [
        "20261128T000000000000Z", "latest"]
