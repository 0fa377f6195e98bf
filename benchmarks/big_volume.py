"""A big volume in bounded memory: peak resident memory of ``miss convert`` of a
1024 x 1024 x 565 int16 gzipped NIfTI (1.13 GB of voxels), over the CLI's baseline.

    .venv/bin/python benchmarks/big_volume.py [--size 1024,1024,565] [--mid 512,512,565]
                                  [--level 600] [--before /work/main/.venv/bin/miss]

The volume is the CThead (``$MISS_CTHEAD``, else ../shared/datasets beside the repo)
resampled linearly to ``--size`` and written gzipped, plane by plane (nibabel's header,
then the planes through ``gzip``), into a temporary folder that goes when the run ends:
the writer holds one plane, and the file is never kept. Each ``miss convert`` runs as
its own process watched from outside (psutil, every 20 ms): the peak of the sum of the
resident memory of its process tree. The baseline is ``miss convert`` of a tiny volume
(CThead resampled to 32 x 32 x 15) at the same level, its second run (the first
compiles and caches kernels). ``--before`` names the ``miss`` of a
checkout without this change (main): its rows are its default and ``--chunks auto``.
The mid-sized volume (296 MB of voxels, over the default budget of 256 MB) shows what
blocks cost against one pass (the budget raised) where one pass still fits.

Writes ``results/big_volume.md``.
"""

from __future__ import annotations

import argparse
import gzip
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from common import markdown_table, save, tree_rss
from scale import _axis, _cthead

#: CThead's skin.
LEVEL = 600.0
SIZE = (1024, 1024, 565)
#: A volume over the default budget that one pass can still hold (296 MB of voxels).
MID = (512, 512, 565)
#: Seconds between two looks at the process tree's memory.
POLL = 0.02


def cthead_planes(size: tuple[int, int, int]) -> Iterator[np.ndarray]:
    """CThead linearly resampled to ``size`` (int16), its (X, Y) planes z in order: the
    resampled volume is never whole, only CThead (15 MB) and one plane are."""
    from miss.io import load_volume

    data = load_volume(_cthead()).data
    data = _axis(_axis(data, 0, size[0]), 1, size[1])  # (X, Y, 113)
    old = data.shape[2]
    for z in np.linspace(0.0, old - 1.0, size[2]):
        k = min(int(z), old - 2)
        a, b = data[:, :, k].astype(np.float32), data[:, :, k + 1].astype(np.float32)
        yield np.rint(a + np.float32(z - k) * (b - a)).astype(np.int16)


def write_gz_nifti(path: Path, size: tuple[int, int, int], planes: Iterator[np.ndarray]) -> Path:
    """A plain NIfTI-1 ``.nii.gz`` of int16 ``planes`` (each (X, Y)), written one plane at
    a time: nibabel makes the header, ``gzip`` takes the planes as they come. The voxel
    sizes keep CThead's extent (256 x 256 x 226 mm)."""
    import nibabel as nib

    header = nib.Nifti1Header()
    header.set_data_shape(size)
    header.set_data_dtype(np.int16)
    affine = np.diag([256 / size[0], 256 / size[1], 226 / size[2], 1.0])
    header.set_sform(affine, code=1)
    header.set_qform(affine, code=1)
    header["vox_offset"] = 352
    with gzip.open(path, "wb", compresslevel=1) as out:
        out.write(header.binaryblock)
        out.write(b"\0" * 4)  # no extensions
        for plane in planes:
            out.write(np.asarray(plane, dtype="<i2").tobytes(order="F"))
    return path


def tree_peak(command: Sequence[str], env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``command``; the highest sum of its process tree's resident memory (MB), and
    its seconds."""
    start = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    peak = tree_rss(proc, poll=POLL)
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{err.decode()[-2000:]}")
    return {"peak_mb": peak, "seconds": time.perf_counter() - start}


def _convert(miss: str, source: Path, out: Path, level: float, *extra: str) -> list[str]:
    return [miss, "convert", str(source), "-o", str(out), "--level", f"{level:g}", *extra]


#: (row, which ``miss``, which volume, extra options, ``MISS_IN_MEMORY_MAX_MB`` or None)
Variant = tuple[str, str, str, tuple[str, ...], str | None]


def variants(args: argparse.Namespace) -> list[Variant]:
    """main's default and ``--chunks auto`` on the big volume, this checkout's default on
    it, and on the mid-sized one this checkout's default (over the budget: blocks) and
    one pass (the budget raised to 1024 MB)."""
    rows: list[Variant] = []
    if not args.skip_before and Path(args.before).is_file():
        rows += [("before (main)", args.before, "big", (), None),
                 ("before (main), --chunks auto", args.before, "big", ("--chunks", "auto"), None)]  # fmt: skip
    rows += [("after", args.after, "big", (), None)]
    if args.mid:
        rows += [("after", args.after, "mid", (), None),
                 ("after, one pass (MISS_IN_MEMORY_MAX_MB=1024)", args.after, "mid", (), "1024")]  # fmt: skip
    return rows


def measure(variant: Variant, files: dict[str, Path], folder: Path, level: float) -> dict[str, Any]:
    """One variant: its baseline (the tiny volume's second run) and its run, MB and s."""
    _, miss, volume, extra, budget = variant
    env = dict(os.environ)
    env.pop("MISS_IN_MEMORY_MAX_MB", None)
    if budget is not None:
        env["MISS_IN_MEMORY_MAX_MB"] = budget
    out = folder / "out.glb"
    tree_peak(_convert(miss, files["tiny"], out, level), env)  # kernels compiled, caches warm
    base = tree_peak(_convert(miss, files["tiny"], out, level), env)
    run = tree_peak(_convert(miss, files[volume], out, level, *extra), env)
    return {"baseline": base, "run": run, "over_mb": run["peak_mb"] - base["peak_mb"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default=",".join(map(str, SIZE)))
    parser.add_argument("--mid", default=",".join(map(str, MID)), help="'' for none")
    parser.add_argument("--level", type=float, default=LEVEL)
    parser.add_argument("--before", default="/work/main/.venv/bin/miss")
    parser.add_argument("--after", default=str(Path(sys.executable).parent / "miss"))
    parser.add_argument("--skip-before", action="store_true", help="only this checkout's rows")
    args = parser.parse_args()
    sizes = {"tiny": (32, 32, 15), "big": _size(args.size)}
    if args.mid:
        sizes["mid"] = _size(args.mid)
    with tempfile.TemporaryDirectory(prefix="miss-big-") as tmp:
        folder = Path(tmp)
        files = {
            name: write_gz_nifti(folder / f"{name}.nii.gz", size, cthead_planes(size))
            for name, size in sizes.items()
        }
        rows, data = [], []
        for variant in variants(args):
            got = measure(variant, files, folder, args.level)
            size, mb = sizes[variant[2]], files[variant[2]].stat().st_size / 1e6
            volume = (
                f"{'x'.join(map(str, size))} ({np.prod(size) * 2 / 1e9:.2f} GB, {mb:.0f} MB gz)"
            )
            data.append({"variant": variant[0], "volume": volume, **got})
            rows.append([variant[0], volume, f"{got['baseline']['peak_mb']:.0f}",
                         f"{got['run']['peak_mb']:.0f}", f"{got['over_mb']:.0f}",
                         f"{got['run']['seconds']:.1f}"])  # fmt: skip
            print(rows[-1], flush=True)
    title = (
        f"`miss convert` of int16 .nii.gz volumes (CThead resampled), level {args.level:g}, "
        "default job; peak RSS of the process tree, MB\n\n"
    )
    header = ["variant", "volume (voxels)", "baseline", "peak", "over baseline", "seconds"]
    table = title + markdown_table(header, rows)
    print(table)
    save("big_volume", {"level": args.level, "runs": data}, table)


def _size(text: str) -> tuple[int, int, int]:
    x, y, z = (int(n) for n in text.split(","))
    return x, y, z


if __name__ == "__main__":
    os.environ.setdefault("VTK_SMP_MAX_THREADS", "2")
    main()
