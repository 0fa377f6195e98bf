"""Each account's disk use and its quota (``MISS_QUOTA_MB``).

An account uses what its volumes take on disk (voxels, label map, thumbnails) and the
files of the models it queued (``submitted_by``: the models it made, on its own volumes
or on one shared with everyone such as the demo). A model's ``worker.log`` is the
server's record, not the account's data, and is not counted. Sizes are read from the
data folder each time, so a deleted volume or a failed job's removed files free their
room at once, whichever server process removed them.

Uploads and new jobs of an account at or over its quota get 507 (an upload larger than
the whole quota, 413); administrators see every account's use (``GET /api/admin/usage``,
``miss user usage``).
"""

from __future__ import annotations

import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from miss.errors import DiskFull
from miss.server.accounts import User, list_users
from miss.server.core.errors import UploadTooLarge
from miss.server.storage.store import Store

MB = 1024 * 1024
#: Files of a model's folder that are not the account's model: the worker's log and the
#: viewer's marks (``jobs.turn``).
NOT_COUNTED = frozenset({"worker.log", ".watched", ".shown"})


class OverQuota(DiskFull):
    """An account's volumes and models fill its disk quota (507)."""


@dataclass(frozen=True)
class Usage:
    """What one account takes on disk: ``bytes`` in its ``volumes`` and ``models``."""

    account: str
    volumes: int = 0
    models: int = 0
    bytes: int = 0


def folder_bytes(folder: Path, skip: frozenset[str] = frozenset()) -> int:
    """Bytes of the files under ``folder`` (0 when it is gone); names in ``skip`` at its
    top are left out. Symbolic links are not followed."""
    total = 0
    try:
        entries = list(os.scandir(folder))
    except OSError:  # removed meanwhile, or never made (a queued job)
        return 0
    for entry in entries:
        if entry.name in skip:
            continue
        try:
            if entry.is_dir(follow_symlinks=False):
                total += folder_bytes(Path(entry.path))
            elif entry.is_file(follow_symlinks=False):
                total += entry.stat(follow_symlinks=False).st_size
        except OSError:  # removed meanwhile
            continue
    return total


def usage(store: Store) -> dict[str, Usage]:
    """Every account's use by name ("" for what nobody owns: the demo and its models)."""
    names = {u.id: u.name for u in list_users(store)}
    volumes: dict[str, int] = defaultdict(int)
    models: dict[str, int] = defaultdict(int)
    sizes: dict[str, int] = defaultdict(int)
    for volume in store.list_volumes():
        name = names.get(volume.owner_id or "", "")
        volumes[name] += 1
        sizes[name] += folder_bytes(store.volume_dir(volume.id))
    for model in store.list_models():
        name = model.submitted_by or ""
        models[name] += 1
        sizes[name] += folder_bytes(store.model_dir(model.id), NOT_COUNTED)
    accounts = [*names.values(), *(n for n in sizes if n not in names.values())]
    return {n: Usage(n, volumes[n], models[n], sizes[n]) for n in accounts}


def used_by(store: Store, user: User) -> int:
    """Bytes ``user``'s volumes and the models it queued take on disk."""
    total = sum(folder_bytes(store.volume_dir(v.id)) for v in store.list_volumes(user.id))
    for model in store.models_submitted_by(user.name):
        total += folder_bytes(store.model_dir(model), NOT_COUNTED)
    return total


def check(store: Store, user: User, quota: int, adding: int = 0) -> None:
    """Refuse (507) when ``user`` already takes ``quota`` bytes or more, or would with
    ``adding`` bytes more; 413 when ``adding`` alone is over the quota. 0: no quota."""
    if quota <= 0:
        return
    if adding > quota:
        raise UploadTooLarge(
            f"this upload ({adding / MB:.0f} MB) is larger than your account's whole disk "
            f"quota of {quota / MB:g} MB (MISS_QUOTA_MB); ask an administrator to raise "
            "the quota."
        )
    used = used_by(store, user)
    if used >= quota or used + adding > quota:
        raise refusal(used, quota)


def refusal(used: int, quota: int, why: str = "") -> OverQuota:
    """The 507 for an account that takes ``used`` bytes of its ``quota``; ``why`` says
    what would take it over, if anything."""
    state = f"{why}: " if why else ""
    return OverQuota(
        f"your account's disk quota is full ({state}its volumes and models take "
        f"{used / MB:.0f} MB of {quota / MB:g} MB, MISS_QUOTA_MB); delete volumes or models "
        "you no longer need (DELETE /api/volumes/{id} or /api/models/{id}), or ask an "
        "administrator to raise the quota."
    )
