"""``miss backup`` while the server runs and a job writes, ``miss restore`` into a fresh
folder: the restored server has the same users, volumes, models, links and room history,
and every file is equal."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text
from support import ADMIN_PASSWORD
from support.pg import database_url, sqlalchemy_url
from support.server_app import started as start_logged_in

from miss.cli import main
from miss.errors import BadParameter
from miss.server.storage.backup import MANIFEST, backup, restore
from miss.server.storage.db import Base

#: Tables whose every row the restored database holds unchanged; ``models`` too but for
#: the job that ran during the backup, ``audit`` up to the backup.
SAME = ("users", "sessions", "volumes", "identities", "shares", "room_events", "secrets")


def rows(url: str) -> dict[str, dict[Any, tuple[Any, ...]]]:
    """Every row of every table, by primary key."""
    engine = create_engine(url)
    out: dict[str, dict[Any, tuple[Any, ...]]] = {}
    try:
        with engine.connect() as conn:
            for table in Base.metadata.sorted_tables:
                key = [c.name for c in table.primary_key.columns]
                found = conn.execute(text(f"SELECT * FROM {table.name}")).mappings()
                out[table.name] = {
                    tuple(r[k] for k in key): tuple(
                        json.dumps(v, sort_keys=True) if isinstance(v, dict | list) else v
                        for v in r.values()
                    )
                    for r in found
                }
    finally:
        engine.dispose()
    return out


def started(data: Path) -> TestClient:
    return start_logged_in(data, ADMIN_PASSWORD)


@pytest.mark.slow
def test_backup_while_a_job_runs_and_restore_into_a_fresh_folder(
    data_dir: Path, tmp_path: Path, small_nifti: bytes, upload_for, model_for
) -> None:
    source = started(data_dir)
    try:
        assert source.post(
            "/api/users", json={"name": "ann", "password": "ann-password"}
        ).is_success
        volume = upload_for(source, {}, small_nifti)
        model = model_for(source, {}, volume["id"])
        link = source.post("/api/shares", json={"model": model["id"], "can_annotate": True})
        token = link.json()["url"][3:]
        with source.websocket_connect(f"/ws/rooms/{model['id']}") as ws:
            assert ws.receive_json()["type"] == "welcome"
            ws.send_json({"type": "chat", "text": "before the backup"})
            assert ws.receive_json()["type"] == "chat"
        demo = next(v for v in source.get("/api/volumes").json() if v["id"] != volume["id"])
        r = source.post("/api/models", json={"volume": demo["id"], "level": 300})
        job = r.json()["id"]
        deadline = time.monotonic() + 60
        while source.get(f"/api/models/{job}").json()["status"] != "running":
            assert time.monotonic() < deadline
            time.sleep(0.05)

        done = backup(data_dir, sqlalchemy_url(data_dir), tmp_path / "backup")
        running = source.get(f"/api/models/{job}").json()["status"]
        source.app.state.store.appender.flush()
        before = rows(sqlalchemy_url(data_dir))
    finally:
        source.__exit__(None, None, None)
    assert running == "running", "the job ended before the backup did: make it longer"
    manifest = json.loads((tmp_path / "backup" / MANIFEST).read_text())
    assert done.files == len(manifest["files"]) > 0 and manifest["vanished"] == []

    with pytest.raises(BadParameter, match="not an empty folder"):
        restore(tmp_path / "backup", data_dir, sqlalchemy_url(data_dir))
    fresh = tmp_path / "restored"
    restore(tmp_path / "backup", fresh, sqlalchemy_url(fresh))
    after = rows(sqlalchemy_url(fresh))
    for table in SAME:
        assert after[table] == before[table], table
    assert set(after["audit"]) <= set(before["audit"])
    assert {k: v for k, v in after["models"].items() if k != (job,)} == {
        k: v for k, v in before["models"].items() if k != (job,)
    }
    for relative, entry in manifest["files"].items():  # each equal to the source's
        assert (fresh / relative).stat().st_size == entry["bytes"]
        if job not in relative:
            assert (fresh / relative).read_bytes() == (data_dir / relative).read_bytes()

    again = started(fresh)
    try:
        assert {v["id"] for v in again.get("/api/volumes").json()} == {volume["id"], demo["id"]}
        assert (
            again.get(f"/api/models/{model['id']}/model.glb").content
            == (data_dir / "models" / model["id"] / "model.glb").read_bytes()
        )
        assert again.get(f"/s/{token}", follow_redirects=False).status_code < 400
        events = again.get(f"/api/models/{model['id']}/room/events").json()
        assert [e["data"].get("text") for e in events if e["kind"] == "chat"] == [
            "before the backup"
        ]
        login = {"username": "ann", "password": "ann-password"}
        assert again.post("/api/auth/login", json=login).status_code == 200
        assert again.get(f"/api/models/{job}").json()["status"] in ("queued", "running", "done")
    finally:
        again.__exit__(None, None, None)


def test_backup_and_restore_commands(data_dir: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    url = database_url(data_dir)
    if url:
        monkeypatch.setenv("MISS_DATABASE_URL", url)
    assert main(["backup", str(tmp_path / "b"), "--data-dir", str(data_dir)]) == 0
    assert "backed up" in capsys.readouterr().out
    assert main(["backup", str(tmp_path / "b"), "--data-dir", str(data_dir)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    if url:
        monkeypatch.setenv("MISS_DATABASE_URL", database_url(tmp_path / "r"))
    assert main(["restore", str(tmp_path / "b"), "--data-dir", str(tmp_path / "r")]) == 0
    assert "restored" in capsys.readouterr().out
