"""``miss restore`` of a crafted backup: a manifest that names a path out of the backup
or out of the data folder (``../escaped/pwned.txt``, an absolute path, a ``database``
field pointing elsewhere) or a symbolic link in the backup is refused whole, before
anything is written: one line naming the entry, exit 2, nothing outside touched."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from support.pg import database_url, sqlalchemy_url

from miss.cli import main
from miss.server.storage.backup import MANIFEST, backup

PWNED = b"written by a crafted backup"


@pytest.fixture
def made(data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A real backup of the seeded data folder; restores go to ``tmp_path/r``."""
    backup(data_dir, sqlalchemy_url(data_dir), tmp_path / "backup")
    if url := database_url(tmp_path / "r"):
        monkeypatch.setenv("MISS_DATABASE_URL", url)
    return tmp_path / "backup"


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def edit(backup_dir: Path, change: dict[str, Any]) -> None:
    """Merge ``change`` into the manifest (``files`` entries added to the listed ones)."""
    manifest = json.loads((backup_dir / MANIFEST).read_text())
    manifest["files"].update(change.pop("files", {}))
    manifest.update(change)
    (backup_dir / MANIFEST).write_text(json.dumps(manifest))


def refused(backup_dir: Path, capsys: pytest.CaptureFixture[str], named: str) -> None:
    target = backup_dir.parent / "r"
    assert main(["restore", str(backup_dir), "--data-dir", str(target)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("miss: will not restore") and err.count("\n") == 1, err
    assert named in err, err
    assert not target.exists(), "the restore wrote into the data folder before refusing"


@pytest.mark.parametrize("key", ["../escaped/pwned.txt", "volumes/../../escaped/pwned.txt"])
def test_a_manifest_path_out_of_the_data_folder_is_refused(
    made: Path, capsys: pytest.CaptureFixture[str], key: str
) -> None:
    # where the old restore read it from: files/KEY, i.e. beside files/
    (made / "files" / key).parent.mkdir(parents=True, exist_ok=True)
    (made / "files" / key).write_bytes(PWNED)
    edit(made, {"files": {key: {"bytes": len(PWNED), "sha256": sha(PWNED)}}})
    refused(made, capsys, key)
    assert not (made.parent / "escaped").exists()


def test_an_absolute_manifest_path_is_refused(
    made: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    victim = made.parent / "victim.txt"
    victim.write_bytes(b"precious")  # the old restore copied it onto itself: emptied
    edit(made, {"files": {str(victim): {"bytes": 8, "sha256": sha(b"precious")}}})
    refused(made, capsys, str(victim))
    assert victim.read_bytes() == b"precious"


def test_a_database_field_pointing_out_of_the_backup_is_refused(
    made: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = json.loads((made / MANIFEST).read_text())
    other = made.parent / f"other-server-{manifest['database']}"
    shutil.copyfile(made / manifest["database"], other)  # another server's database
    edit(made, {"database": f"../{other.name}"})
    refused(made, capsys, f"../{other.name}")


def test_a_symbolic_link_in_the_backup_is_refused(
    made: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = json.loads((made / MANIFEST).read_text())
    key = next(k for k in sorted(manifest["files"]) if k.endswith("meta.json"))
    outside = made.parent / "outside-meta.json"
    shutil.copyfile(made / "files" / key, outside)  # same bytes: the checksum holds
    (made / "files" / key).unlink()
    (made / "files" / key).symlink_to(outside)
    refused(made, capsys, key)


def test_a_linked_folder_in_the_backup_is_refused(
    made: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outside = made.parent / "outside-volumes"
    shutil.move(made / "files" / "volumes", outside)
    (made / "files" / "volumes").symlink_to(outside, target_is_directory=True)
    refused(made, capsys, "volumes/")


@pytest.mark.parametrize("key", ["volumes\\..\\..\\x", "C:/x", "volumes/./x", "volumes//x"])
def test_odd_spellings_are_refused_too(
    made: Path, capsys: pytest.CaptureFixture[str], key: str
) -> None:
    """Harmless on Linux (each stays inside), refused as no backup writes them."""
    edit(made, {"files": {key: {"bytes": 0, "sha256": sha(b"")}}})
    refused(made, capsys, repr(key)[1:-1])


def test_an_untouched_backup_still_restores(made: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["restore", str(made), "--data-dir", str(made.parent / "r")]) == 0
    assert "restored" in capsys.readouterr().out
