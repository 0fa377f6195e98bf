"""The attack corpus (``tests/corpus/attacks.py``) against a real ``miss serve``: every
upload that tries to make a reader open another file is refused, or stored without a
byte of that file; none gets a 5xx."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from corpus.attacks import Attack, attacks, distinctive
from support.realserver import Server, serving

from miss.server.storage import chunked


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("corpus-attacks")
    with serving(folder / "data", folder / "server.log") as running:
        yield running


def voxel_bytes(folder: Path) -> bytes:
    """A stored volume's voxels as bytes, Fortran order (as the volume's source hash)."""
    return np.asarray(chunked.open_array(folder / "data.zarr")[0][:]).tobytes(order="F")


def test_no_attack_reads_outside_its_upload(server: Server, tmp_path: Path) -> None:
    secret = tmp_path / "secret.bin"
    secret.write_bytes(secrets.token_bytes(16384))
    targets = {"secret": secret, "database": server.data_dir / "miss.sqlite3"}
    cases = [a for a in attacks(targets) if "pid 1" not in a.name]
    needles = {a.target: distinctive(a.target, server.proc.pid) for a in cases}
    before = set((server.data_dir / "volumes").iterdir())

    def send(attack: Attack) -> tuple[str, int, str]:
        files = {"file": (attack.filename, attack.content)}
        r = server.http.post("/api/volumes", files=files)
        return attack.name, r.status_code, r.text[:200]

    with ThreadPoolExecutor(2) as pool:
        answers = list(pool.map(send, cases))
    assert [a for a in answers if a[1] >= 500] == []
    assert [a for a in answers if 400 <= a[1] < 500 and '"detail"' not in a[2]] == []
    stored = set((server.data_dir / "volumes").iterdir()) - before
    leaks = [
        (folder.name, target.name)
        for folder in stored
        for target, needle in needles.items()
        if needle and needle in voxel_bytes(folder)
    ]
    assert leaks == []
    # Stored only where no reader takes the line for a data-file field (a Cyrillic letter
    # in the name): the upload's own LOCAL voxels, which the leak check above looked at.
    accepted = [name for name, code, _ in answers if code < 300]
    assert all("lookalike" in name for name in accepted), accepted
