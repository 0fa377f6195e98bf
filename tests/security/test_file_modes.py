"""The data folder, the database and backups are owner-only, whatever the umask of the
shell that started MISS: under the usual 022 another local account could read the
identity table (patients' names) and every volume."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

from support.pg import database_url
from support.realserver import serving

#: Runs its arguments under the umask most shells have.
UMASK_022 = ("sh", "-c", 'umask 022; exec "$@"', "sh")


def open_to_others(top: Path) -> list[str]:
    """``top`` and everything under it that has a group or other permission bit."""
    paths = [top, *top.rglob("*")]
    return [
        f"{p} {stat.S_IMODE(p.lstat().st_mode):o}"
        for p in paths
        if not p.is_symlink() and p.lstat().st_mode & 0o077
    ]


def miss(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*UMASK_022, sys.executable, "-m", "miss", *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_serve_and_backup_under_umask_022_write_owner_only(tmp_path: Path) -> None:
    data = tmp_path / "data"  # made by the server
    with serving(data, tmp_path / "server.log", wrap=UMASK_022) as server:
        demo = server.http.get("/api/volumes").json()[0]["id"]
        r = server.http.post("/api/models", json={"volume": demo, "level": 300, "sample_rate": 4})
        assert r.status_code == 202, r.text
        assert server.wait(r.json()["id"], ("done", "failed"))["status"] == "done"
        assert stat.S_IMODE(data.stat().st_mode) == 0o700
        names = {p.name for p in data.rglob("*")}
        assert {"data.zarr", "meta.json"} <= names, names  # a volume and a model stored
        if not database_url(data):
            assert {"miss.sqlite3", "miss.sqlite3-wal"} <= names, names
        assert open_to_others(data) == []
    backup = tmp_path / "backup"
    env_url = database_url(data)
    done = subprocess.run(
        [*UMASK_022, sys.executable, "-m", "miss", "backup", str(backup), "--data-dir", str(data)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **({"MISS_DATABASE_URL": env_url} if env_url else {})},
    )
    assert done.returncode == 0, done.stderr
    assert (backup / "manifest.json").is_file() and (backup / "files" / "models").is_dir()
    assert open_to_others(backup) == []


def test_an_existing_open_data_folder_is_tightened_and_said(tmp_path: Path) -> None:
    """A data folder made under 022 by an older MISS: the next command closes it."""
    data = tmp_path / "data"
    data.mkdir(mode=0o755)
    data.chmod(0o755)
    database = data / "miss.sqlite3"
    database.touch()
    database.chmod(0o644)
    done = miss("user", "add", "ann", "--data-dir", str(data), stdin="ann-password-long\n")
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(data.stat().st_mode) == 0o700
    if not database_url(data):
        assert stat.S_IMODE(database.stat().st_mode) == 0o600
        assert f"{database} was readable by other accounts" in done.stderr
    assert f"{data} was readable by other accounts; made it owner-only" in done.stderr
