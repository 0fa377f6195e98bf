"""Levels of detail in the server: a job over ``MISS_LOD_TRIANGLES`` writes a 3D Tiles
tileset beside its files, and its tiles are served with the model's access rules: the
owner (here the administrator, the demo's owner) and a link's guests, nobody else."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient
from support.pg import copy_seed, settings_for
from support.server_app import ADMIN_PASSWORD, log_in, wait_for_model

from miss.server.app import create_app

BUDGET = 20_000


@pytest.fixture(scope="module")
def client(seeded_dir: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """This module's app with a low triangle budget; its workers inherit the environment."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("MISS_LOD_TRIANGLES", str(BUDGET))
        data = copy_seed(seeded_dir, tmp_path_factory.mktemp("lod") / "data")
        with TestClient(create_app(settings_for(data, admin_password=ADMIN_PASSWORD))) as c:
            log_in(c)
            yield c


def model(client: TestClient, volume: str, **form: Any) -> dict[str, Any]:
    r = client.post("/api/models", json={"volume": volume, **form})
    assert r.status_code in (200, 202), r.text
    done = wait_for_model(client, r.json()["id"])
    assert done["status"] == "done", done
    return done


@pytest.mark.slow
def test_a_model_over_the_budget_has_levels_of_detail(
    client: TestClient, demo_id: str, people: dict[str, dict[str, str]]
) -> None:
    large = model(client, demo_id, level=300, decimate="none")
    assert large["stats"]["triangles"] > BUDGET
    assert large["stats"]["lod"]["tiles"] > 8 and "lod" in large["stats"]["seconds"]
    url = large["lod"]
    assert url.startswith(f"/api/models/{large['id']}/lod/tileset.json?v=")
    tileset = client.get(url)
    assert tileset.status_code == 200 and tileset.headers["content-type"] == "application/json"
    root = json.loads(tileset.content)["root"]
    assert root["refine"] == "REPLACE" and root["extras"]["triangles"] < BUDGET
    base = url.split("tileset.json")[0]
    tile = client.get(base + root["content"]["uri"])
    assert tile.status_code == 200 and tile.content[:4] == b"glTF"
    assert tile.headers["content-type"] == "model/gltf-binary"
    again = client.get(
        base + root["content"]["uri"], headers={"If-None-Match": tile.headers["etag"]}
    )
    assert again.status_code == 304
    # the full-resolution downloads are as they were
    assert client.get(f"/api/models/{large['id']}/model.stl").status_code == 200
    # anybody else: as if there were no such model
    for path in (url, base + root["content"]["uri"]):
        assert client.get(path, headers=people["alice"]).status_code == 404
    for name in ("..%2Fmodel.glb", "tiles/x.glb", "tiles/r9.glb", "worker.log"):
        assert client.get(base + name).status_code == 404


def test_a_link_serves_the_tiles_to_its_guests(client: TestClient, demo_id: str) -> None:
    large = model(client, demo_id, level=300, decimate="none")
    r = client.post("/api/shares", json={"model": large["id"]})
    assert r.status_code == 201, r.text
    guest = TestClient(client.app)  # no login: the link only
    info = guest.get(f"{r.json()['url']}/info").json()
    (shared,) = info["models"]
    assert shared["lod"].startswith(f"{r.json()['url']}/models/{large['id']}/lod/tileset.json")
    tileset = guest.get(shared["lod"])
    assert tileset.status_code == 200 and tileset.headers["cache-control"] == "no-store"
    base = shared["lod"].split("tileset.json")[0]
    assert guest.get(base + "tiles/r.glb").content[:4] == b"glTF"
    assert guest.get(f"/api/models/{large['id']}/lod/tileset.json").status_code == 401


def test_a_model_within_the_budget_has_none(client: TestClient, demo_id: str) -> None:
    small = model(client, demo_id, level=300, sample_rate=2)
    assert small["stats"]["triangles"] <= BUDGET
    assert small["lod"] is None and "lod" not in small["stats"]
    assert client.get(f"/api/models/{small['id']}/lod/tileset.json").status_code == 404


def test_a_tileset_is_replaced_whole(tmp_path: Any) -> None:
    """Written into a hidden folder and renamed: an older tileset goes at once, and no
    half-written folder is left beside it."""
    from miss.server.jobs.worker import write_tree_atomic

    folder = tmp_path / "lod"
    write_tree_atomic(folder, {"tileset.json": b"{}", "tiles/r.glb": b"1", "tiles/r0.glb": b"2"})
    write_tree_atomic(folder, {"tileset.json": b"{ }", "tiles/r.glb": b"3"})
    assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*.*")) == [
        "tiles/r.glb",
        "tileset.json",
    ]
    assert (folder / "tiles/r.glb").read_bytes() == b"3"
    assert [p.name for p in tmp_path.iterdir()] == ["lod"]
