"""A link's guests never read why a model could not be made (the reason may name the
server's folders or the scan's figures, "no piece of bone (310 HU) is at least ..."):
not in the link's info, not in the answer for the model's file. The owner reads it."""

from __future__ import annotations

from pathlib import Path

import httpx
from support.realserver import serving
from test_access import own_model


def test_guests_of_a_failed_model_read_no_reason(tmp_path: Path) -> None:
    with serving(tmp_path / "data", tmp_path / "server.log", env={"MISS_DEMO": "0"}) as running:
        ball = running.model(own_model(running, running.token))["volume"]
        # No piece of a 24-voxel ball is 1e12 mm³: the job fails with the engine's reason.
        failed = running.submit(ball, level=0, min_size_mm3=1e12)
        reason = running.wait(failed, ("failed",))["error"]
        assert reason, "the owner reads why"
        link = running.http.post("/api/shares", json={"model": failed}).json()["url"]
        with httpx.Client(base_url=running.url, timeout=60) as guest:
            answers = {
                path: guest.get(path)
                for path in (
                    f"{link}/info",
                    f"{link}/model.glb",
                    f"{link}/models/{failed}/model.glb",
                    f"{link}/models/{failed}/lod/tileset.json",
                    link,
                )
            }
    for path, answer in answers.items():
        assert reason not in answer.text, (path, answer.text)
    assert "could not be made" in answers[f"{link}/info"].text
    assert "could not be made" in answers[f"{link}/models/{failed}/model.glb"].json()["detail"]
