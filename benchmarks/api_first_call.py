"""The Python API's first call, as a notebook user meets it: a fresh process, imports done,
then the whole job timed from its first call (everything that call loads included).

    .venv/bin/python benchmarks/api_first_call.py [--repeats 7] [--level 1500]

MISS: ``miss.load_volume`` -> ``extract_surface`` -> ``decimate(method="quadric",
reduce=0.9, measure=False)`` -> ``export`` GLB and VRML, files written. The peer: the same
job composed from nibabel, VTK's flying edges, meshoptimizer and trimesh
(``peer_script.py``), its imports done before its clock starts too. Both read the paper's
volume (CThead at 256 x 256 x 225, uncompressed NIfTI); they take turns (round robin),
after one untimed run each that writes the byte-code and kernel caches an installed
package has. Each child also times a second, warm call in the same process: the
difference is what the first call pays.

Each child also times its own imports (``import miss``; the peer's modules): what a user
meets is imports and first call together, the last two columns.

Writes ``results/api_first_call.{json,md}``; the target (issue 41): MISS's first call at
least 1.5x faster than the peer's (peer / MISS >= 1.5).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from common import markdown_table, median, paper_volume_file, save

HERE = Path(__file__).resolve().parent
OUT = Path(tempfile.gettempdir()) / "miss-bench-api"

MISS_CHILD = """
import time
began = time.perf_counter()
import json, sys
from pathlib import Path
import miss
imports = time.perf_counter() - began
out = Path(sys.argv[3])

def job():
    vol = miss.load_volume(sys.argv[1])
    mesh = miss.extract_surface(vol, float(sys.argv[2]))
    mesh, _ = miss.decimate(mesh, method="quadric", reduce=0.9, measure=False)
    (out / "miss.glb").write_bytes(miss.export(mesh, "glb"))
    (out / "miss.wrl").write_bytes(miss.export(mesh, "wrl"))
    return mesh.n_triangles

times = []
for _ in range(2):
    start = time.perf_counter()
    triangles = job()
    times.append(time.perf_counter() - start)
print(json.dumps({"imports": imports, "first": times[0], "warm": times[1], "triangles": triangles}))
"""

PEER_CHILD = """
import time
began = time.perf_counter()
import json, sys
from pathlib import Path
sys.path.insert(0, sys.argv[4])
import peer_script, trimesh  # noqa: F401  (what main() loads, loaded before the clock)
imports = time.perf_counter() - began
out = Path(sys.argv[3])
times = []
for _ in range(2):
    start = time.perf_counter()
    peer_script.main(sys.argv[1], str(out / "peer.glb"), str(out / "peer.wrl"),
                     float(sys.argv[2]), 0.9)
    times.append(time.perf_counter() - start)
print(json.dumps({"imports": imports, "first": times[0], "warm": times[1]}))
"""

CHILDREN = {"MISS": MISS_CHILD, "peer (nibabel + VTK + meshoptimizer + trimesh)": PEER_CHILD}


def run_child(code: str, volume: Path, level: float) -> dict[str, Any]:
    """One fresh process: its first and warm seconds (and MISS's triangle count)."""
    argv = [sys.executable, "-c", code, str(volume), f"{level:g}", str(OUT), str(HERE)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=600, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--level", type=float, default=1500.0)
    args = parser.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    volume = paper_volume_file()
    for code in CHILDREN.values():
        run_child(code, volume, args.level)  # untimed: caches written
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in CHILDREN}
    for _ in range(args.repeats):
        for name, code in CHILDREN.items():
            runs[name].append(run_child(code, volume, args.level))
    firsts = {name: median([r["first"] for r in rs]) for name, rs in runs.items()}
    totals = {name: median([r["imports"] + r["first"] for r in rs]) for name, rs in runs.items()}
    peer, peer_total = firsts[list(CHILDREN)[1]], totals[list(CHILDREN)[1]]
    rows = [
        [
            name,
            f"{median([r['imports'] for r in rs]):.3f}",
            f"{firsts[name]:.3f}",
            f"{median([r['warm'] for r in rs]):.3f}",
            f"{peer / firsts[name]:.2f}",
            f"{totals[name]:.3f}",
            f"{peer_total / totals[name]:.2f}",
        ]
        for name, rs in runs.items()
    ]
    header = ["first call in a fresh process", "imports, s", "first, s", "warm, s",
              "peer / this", "imports + first, s", "peer / this"]  # fmt: skip
    table = markdown_table(header, rows)
    print(table)
    save("api_first_call", {"runs": runs, "level": args.level}, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
