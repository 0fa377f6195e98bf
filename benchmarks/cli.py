"""Speed a person feels: whole ``miss`` processes timed from outside, beside a peer script.

    .venv/bin/python benchmarks/cli.py [--repeats 7] [--level 1500] [--volume V] [--info F]

Each command runs as a fresh process under ``/usr/bin/time -v``, imports and all: wall
seconds from outside (the interval around the process), peak resident memory (max RSS)
and CPU seconds from ``time``. The commands take turns inside every repeat (round robin),
after one untimed run each that writes the byte-code caches an installed package has.

- ``miss --help``; ``miss info`` on CThead.nhdr;
- ``miss convert`` of the paper's volume (CThead at 256 x 256 x 225, uncompressed NIfTI)
  at the bone level to GLB and VRML, quadric decimation to 10 % of the triangles, as a
  user runs it;
- the same with ``--measure``: it also measures its deviation from the undecimated
  surface (with the native kernels: numba does not load);
- ``miss convert`` as a user runs it when they change nothing: the ``guaranteed`` schedule,
  the model held within 0.002 of the diagonal (measured while decimating; quadric hands
  over to schroeder where it does not hold), so it keeps as many triangles as the bound
  needs, not 10 %;
- ``peer_script.py``: the same job composed from nibabel, VTK, meshoptimizer and trimesh.

Afterwards both GLB files are read back (trimesh) and each decimated surface's deviation
from its own undecimated one is measured with ``miss.measure._jit`` (same samples and seed).

Writes ``results/cli.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from common import RESULTS, markdown_table, median, paper_volume_file, round_robin, save
from paper import default_cthead

HERE = Path(__file__).resolve().parent
OUT = Path(tempfile.gettempdir()) / "miss-bench-cli"
REDUCE = 0.9
HELP, INFO = "miss --help", "miss info"
CONVERT, MEASURED, PEER = "miss convert", "miss convert --measure", "peer script"
HELD = "miss convert (default: bound held)"
TARGETS = {HELP: "<= 0.15 s", INFO: "<= 0.40 s", CONVERT: ">= 1.5x, RSS <= peer's"}


def commands(volume: Path, info: Path, level: float) -> dict[str, list[str]]:
    """Each timed command's argv (the ``miss`` command is ``python -m miss``)."""
    miss = [sys.executable, "-m", "miss"]
    job = [str(volume), "--level", f"{level:g}", "--decimate", "quadric", "--reduce", str(REDUCE)]
    job += ["--schedule", "paper"]  # to 10 % like the peer script, as before bounds were held
    outputs = ["-o", str(OUT / "miss.glb"), "-o", str(OUT / "miss.wrl")]
    return {
        HELP: [*miss, "--help"],
        INFO: [*miss, "info", str(info)],
        CONVERT: [*miss, "convert", *job, *outputs],
        MEASURED: [*miss, "convert", *job, *outputs, "--measure"],
        HELD: [*miss, "convert", str(volume), "--level", f"{level:g}",
               "-o", str(OUT / "held.glb"), "-o", str(OUT / "held.wrl")],
        PEER: [sys.executable, str(HERE / "peer_script.py"), str(volume),
               str(OUT / "peer.glb"), str(OUT / "peer.wrl"), f"{level:g}", str(REDUCE)],
    }  # fmt: skip


def _child_env() -> dict[str, str]:
    """This environment, byte-code caches allowed (an installed package has them)."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def timed(argv: list[str]) -> dict[str, float]:
    """One run under ``/usr/bin/time -v``: its peak RSS (MiB) and CPU seconds."""
    proc = subprocess.run(
        ["/usr/bin/time", "-v", *argv], capture_output=True, text=True, env=_child_env(),
        timeout=600, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv[:4])} ... failed:\n{proc.stderr[-2000:]}")
    fields = dict(line.strip().rsplit(": ", 1) for line in proc.stderr.splitlines() if ": " in line)
    return {
        "rss_mib": int(fields["Maximum resident set size (kbytes)"]) / 1024,
        "cpu_seconds": float(fields["User time (seconds)"])
        + float(fields["System time (seconds)"]),
    }


def bench(argvs: dict[str, list[str]], repeats: int) -> dict[str, dict[str, Any]]:
    """Every command once untimed, then ``repeats`` round-robin runs: medians and all runs."""
    OUT.mkdir(parents=True, exist_ok=True)
    for argv in argvs.values():
        timed(argv)
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in argvs}
    candidates: dict[str, Callable[[], None]] = {
        name: (lambda name=name, argv=argv: runs[name].append(timed(argv)))
        for name, argv in argvs.items()
    }
    seconds, _ = round_robin(candidates, repeats)
    return {
        name: {
            "seconds": median(seconds[name]),
            "rss_mib": median([r["rss_mib"] for r in runs[name]]),
            "cpu_seconds": median([r["cpu_seconds"] for r in runs[name]]),
            "runs": seconds[name],
            "rss_runs": [r["rss_mib"] for r in runs[name]],
        }
        for name in argvs
    }


def _glb_mesh(path: Path) -> Any:
    """The triangles of a GLB file as its buffer holds them (mm, before any node matrix)."""
    import trimesh

    from miss import Mesh

    scene = trimesh.load(str(path), process=False, force="scene")
    (mesh,) = scene.geometry.values()
    return Mesh(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32))


def deviations(volume: Path, level: float) -> dict[str, dict[str, Any]]:
    """Each result read back and measured against its own undecimated surface."""
    import peer_script

    import miss
    from miss.measure._jit import deviation

    references = {
        CONVERT: miss.extract_surface(miss.load_volume(volume), level, normals=False),
        PEER: miss.Mesh(*(a.astype(t) for a, t in zip(
            peer_script.isosurface(str(volume), level), (np.float32, np.int32), strict=True
        ))),
    }  # fmt: skip
    out = {}
    references[HELD] = references[CONVERT]
    for name, stem in ((CONVERT, "miss"), (HELD, "held"), (PEER, "peer")):
        result = _glb_mesh(OUT / f"{stem}.glb")
        dev = deviation(references[name], result)  # 100 000 samples a side, seed 0
        out[name] = {
            "triangles_before": references[name].n_triangles,
            "triangles": result.n_triangles,
            "max_error_mm": dev.max_mm,
            "mean_error_mm": dev.mean_mm,
            "glb_bytes": (OUT / f"{stem}.glb").stat().st_size,
            "wrl_bytes": (OUT / f"{stem}.wrl").stat().st_size,
        }
    return out


COLUMNS = [
    "command", "median wall s", "vs peer script", "median peak RSS MiB", "CPU s",
    "triangles", "max deviation mm", "mean deviation mm", "target",
]  # fmt: skip


def report(res: dict[str, Any]) -> str:
    peer = res["timing"][PEER]
    rows = []
    for name, t in res["timing"].items():
        dev = res["deviation"].get(name if name != MEASURED else CONVERT, {})
        converts = name in (CONVERT, MEASURED, HELD, PEER)
        rows.append([
            name, t["seconds"], f"{peer['seconds'] / t['seconds']:.2f}x" if converts else "",
            t["rss_mib"], t["cpu_seconds"], str(dev.get("triangles", "")),
            f"{dev['max_error_mm']:.3f}" if dev else "",
            f"{dev['mean_error_mm']:.4f}" if dev else "", TARGETS.get(name, ""),
        ])  # fmt: skip
    return (
        f"`miss` as whole processes (`/usr/bin/time -v`, imports included), medians of "
        f"{res['repeats']} alternating runs; convert: {res['volume']}, level {res['level']:g}, "
        f"quadric to {1 - REDUCE:.0%} of the triangles (the default row: the bound held), "
        "GLB + VRML. Deviation: each GLB read "
        "back, against its own undecimated surface (miss.measure._jit, 100 000 samples a side, "
        "seed 0).\n\n" + markdown_table(COLUMNS, rows)
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--level", type=float, default=1500.0, help="the bone level of peers.py")
    parser.add_argument("--volume", help="the job's NIfTI (default: the paper's CThead)")
    parser.add_argument("--info", help="the file for miss info (default: CThead.nhdr)")
    parser.add_argument("--out", default=str(RESULTS), help="folder for cli.json and cli.md")
    args = parser.parse_args(argv)
    volume = Path(args.volume) if args.volume else paper_volume_file()
    info = Path(args.info) if args.info else default_cthead()
    res: dict[str, Any] = {
        "volume": volume.name if args.volume else "CThead 256x256x225 int16 (.nii)",
        "level": args.level,
        "repeats": args.repeats,
        "commands": {k: ["python", *v[1:]] for k, v in commands(volume, info, args.level).items()},
    }
    res["timing"] = bench(commands(volume, info, args.level), args.repeats)
    res["deviation"] = deviations(volume, args.level)
    table = report(res)
    save("cli", res, table, Path(args.out))
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
