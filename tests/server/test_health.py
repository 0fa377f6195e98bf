"""What operators watch: ``/api/health`` (cheap, and ``?deep=1`` with the database, the
data folder and the job runners checked) and ``/metrics`` in Prometheus's text format."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import create_engine


def samples(text: str) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def test_health_stays_cheap_and_deep_checks_everything(make_client) -> None:
    client = make_client()
    assert client.get("/api/health").json()["status"] == "ok"
    r = client.get("/api/health?deep=1")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["status"] == "ok"
    assert body["database"]["ok"] and body["data_folder"]["ok"]
    assert body["job_runners"] == {"ok": True, "alive": 1, "of": 1, "running": 0}
    anonymous = client.get("/api/health?deep=1", headers={"Authorization": ""}).json()
    assert anonymous == {  # a load balancer learns whether, not why
        "status": "ok",
        "version": body["version"],
        "database": {"ok": True},
        "data_folder": {"ok": True},
        "job_runners": {"ok": True},
    }


def test_deep_health_names_what_fails(make_client, tmp_path: Path) -> None:
    client = make_client()
    store = client.app.state.store
    good = store.engine
    store.engine = create_engine(f"sqlite:///{tmp_path}/no/such/folder/db.sqlite3")
    try:
        r = client.get("/api/health?deep=1")
    finally:
        store.engine.dispose()
        store.engine = good
    assert r.status_code == 503, r.text
    body = r.json()
    assert body["status"] == "failing" and not body["database"]["ok"]
    assert "unable to open database file" in body["database"]["error"]
    assert body["data_folder"]["ok"] and body["job_runners"]["ok"]


@pytest.mark.slow
def test_metrics_for_administrators_and_the_scrape_token(
    make_client, monkeypatch: pytest.MonkeyPatch, small_nifti: bytes, upload_for, model_for
) -> None:
    client = make_client()
    admin = dict(client.headers)
    volume = upload_for(client, {}, small_nifti)
    model = model_for(client, {}, volume["id"])
    for _ in range(3):
        assert client.get(f"/api/models/{model['id']}").status_code == 200
    assert client.get("/api/models/0000000000000000").status_code == 404

    done = ("miss_job_seconds_count", frozenset({("outcome", "done")}))
    deadline = time.monotonic() + 10  # the job's thread records it after the worker's exit
    while done not in (got := samples(client.get("/metrics").text)):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    route = frozenset({("method", "GET"), ("route", "/api/models/{model_id}")})
    assert got[("miss_http_requests_total", route | {("status", "200")})] >= 3
    assert got[("miss_http_requests_total", route | {("status", "404")})] == 1
    assert got[("miss_http_request_seconds_count", route)] >= 4
    assert got[("miss_jobs", frozenset({("state", "done")}))] == 1
    assert got[("miss_jobs", frozenset({("state", "queued")}))] == 0
    assert got[done] == 1
    assert got[("miss_room_connections", frozenset())] == 0

    client.headers.clear()
    assert client.get("/metrics").status_code == 401
    client.post("/api/users", json={"name": "nurse", "password": "nurse-password"}, headers=admin)
    login = client.post("/api/auth/login", json={"username": "nurse", "password": "nurse-password"})
    client.cookies.clear()
    nurse = {"Authorization": f"Bearer {login.json()['token']}"}
    assert client.get("/metrics", headers=nurse).status_code == 403
    monkeypatch.setenv("MISS_METRICS_TOKEN", "scrape-token-for-prometheus")
    scraper = {"Authorization": "Bearer scrape-token-for-prometheus"}
    assert client.get("/metrics", headers=scraper).status_code == 200
    assert client.get("/metrics", headers={"Authorization": "Bearer wrong"}).status_code == 401
