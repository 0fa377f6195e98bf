"""What the confined reader sends back is checked before it is believed, read whole or
plane by plane: a reader that a hostile file took over can lie about the voxels (a link
to another file, a short or odd file, a file cut short while it is read), not make the
server read anything else, crash, or run on after its answer."""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from miss.errors import UnreadableVolume
from miss.io.confined import OUT, Limits, Parsed, _parsed, _result

ANSWER = {"volume": {"affine": np.eye(4).tolist(), "meta": {"source_format": "nifti"}}}
VOXELS = np.asfortranarray(np.arange(4 * 3 * 5, dtype=np.int16).reshape(4, 3, 5))


def read(out: Path, whole: bool) -> np.ndarray:
    """The voxels the server takes from ``out``, whole or from their planes."""
    parsed = _parsed(out, ANSWER, whole)
    try:
        if whole:
            assert parsed.volume is not None
            return parsed.volume.data
        assert parsed.streamed is not None
        return np.stack(list(parsed.streamed.planes), axis=2)
    finally:
        parsed.close()


def symlinked(out: Path) -> None:
    np.save(out.parent / "elsewhere.npy", VOXELS)
    (out / "data.npy").symlink_to(out.parent / "elsewhere.npy")


def hard_linked(out: Path) -> None:
    np.save(out.parent / "elsewhere.npy", VOXELS)
    os.link(out.parent / "elsewhere.npy", out / "data.npy")


def truncated(out: Path) -> None:
    np.save(out / "data.npy", VOXELS)
    with (out / "data.npy").open("r+b") as f:
        f.truncate(f.seek(0, 2) - 2)


def too_long(out: Path) -> None:
    np.save(out / "data.npy", VOXELS)
    with (out / "data.npy").open("ab") as f:
        f.write(b"\0\0")


def two_dimensional(out: Path) -> None:
    np.save(out / "data.npy", VOXELS[:, :, 0])


def objects(out: Path) -> None:
    np.save(out / "data.npy", np.empty((2, 2, 2), dtype=object), allow_pickle=True)


def folder(out: Path) -> None:
    (out / "data.npy").mkdir()


ATTACKS: dict[str, Callable[[Path], None]] = {
    "symlink": symlinked,
    "hard link": hard_linked,
    "truncated": truncated,
    "too long": too_long,
    "2-D": two_dimensional,
    "objects": objects,
    "folder": folder,
}


@pytest.mark.parametrize("whole", [True, False], ids=["whole", "planes"])
@pytest.mark.parametrize("attack", ATTACKS)
def test_a_lying_answer_is_refused(tmp_path: Path, attack: str, whole: bool) -> None:
    out = tmp_path / OUT
    out.mkdir()
    ATTACKS[attack](out)
    with pytest.raises(UnreadableVolume, match="file reader"):
        read(out, whole)


@pytest.mark.parametrize("whole", [True, False], ids=["whole", "planes"])
def test_an_honest_answer_is_read_alike_whole_or_by_planes(tmp_path: Path, whole: bool) -> None:
    out = tmp_path / OUT
    out.mkdir()
    np.save(out / "data.npy", VOXELS)
    assert np.array_equal(read(out, whole), VOXELS)
    assert not (out / "data.npy").exists()  # its name is gone once it is open


def test_planes_refuse_c_order_and_values_that_are_not_numbers(tmp_path: Path) -> None:
    out = tmp_path / OUT
    out.mkdir()
    np.save(out / "data.npy", np.ascontiguousarray(VOXELS))
    with pytest.raises(UnreadableVolume, match="unusable voxels"):
        read(out, whole=False)
    values = VOXELS.astype(np.float32)
    values[1, 1, 3] = np.nan
    np.save(out / "data.npy", values)
    with pytest.raises(UnreadableVolume, match="not numbers"):
        read(out, whole=False)


def test_a_file_cut_short_while_its_planes_are_read_is_refused(tmp_path: Path) -> None:
    """As by a process the reader left behind that kept the file open: a short read,
    refused, where a map of the file would have killed the server (SIGBUS)."""
    out = tmp_path / OUT
    out.mkdir()
    np.save(out / "data.npy", VOXELS)
    kept = os.open(out / "data.npy", os.O_WRONLY)
    parsed: Parsed = _parsed(out, ANSWER, whole=False)
    try:
        assert parsed.streamed is not None
        planes = parsed.streamed.planes
        assert np.array_equal(next(planes), VOXELS[:, :, 0])
        os.ftruncate(kept, 200)
        with pytest.raises(UnreadableVolume, match="truncated voxels"):
            list(planes)
    finally:
        os.close(kept)
        parsed.close()


def test_what_the_reader_started_is_killed_before_its_answer_is_read(tmp_path: Path) -> None:
    (tmp_path / OUT).mkdir()
    script = "sleep 300 & echo $! > out/pid; echo '{}' > out/result.json"
    proc = subprocess.Popen(["sh", "-c", script], cwd=tmp_path, start_new_session=True)
    assert _result(tmp_path, proc, Limits(seconds=30)) == {}
    pid = int((tmp_path / OUT / "pid").read_text())
    deadline = time.monotonic() + 10  # SIGKILL was sent: it goes as soon as it is run
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(pid)


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting for its reaper counts as dead)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")
