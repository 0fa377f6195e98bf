"""Typed dependencies: what a route needs, looked up once (tests swap them via overrides)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from starlette.concurrency import run_in_threadpool

from miss.server.db import ModelRow, VolumeRow
from miss.server.jobs import JobQueue
from miss.server.settings import Settings
from miss.server.store import Store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[Store, Depends(get_store)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]


async def get_volume_row(volume_id: str, store: StoreDep) -> VolumeRow:
    """The volume named in the path, or 404 before the route (or its stream) starts."""
    return await run_in_threadpool(store.get_volume, volume_id)


async def get_model_row(model_id: str, store: StoreDep) -> ModelRow:
    return await run_in_threadpool(store.get_model, model_id)


VolumeDep = Annotated[VolumeRow, Depends(get_volume_row)]
ModelDep = Annotated[ModelRow, Depends(get_model_row)]
