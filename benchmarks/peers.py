"""MISS beside today's peers on the paper's volume: each stage, then the whole job.

    .venv/bin/python benchmarks/peers.py [--repeats 7] [--slow-repeats 1] [--level 1500]

The job: read the volume file (CThead at 256 x 256 x 225, uncompressed NIfTI) -> isosurface
-> decimate to 10 % of the triangles -> write GLB and VRML files. Every stage is timed for
each peer on the same input (medians, round-robin repeats); the fastest peer of each stage
make up the "best composed peer pipeline", which then runs end to end, interleaved with
MISS's own job through its public API. Each decimated mesh's deviation from the surface it
was made from is measured with ``miss.measure._jit`` (same seed, same 100 000 samples a side).

VTK runs on its STDThread SMP backend for the peers too (MISS switches it on; a user can
by ``VTK_SMP_BACKEND_IN_USE``), so flying edges uses both cores on either side.

Measurement is not part of the timed MISS job (``decimate(..., measure=False)``) because
no peer measures; ``miss.pipeline.run``, which does, is timed beside it.

Writes ``results/peers.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("VTK_SMP_BACKEND_IN_USE", "STDThread")

import numpy as np  # noqa: E402
import vtk  # noqa: E402
from common import (  # noqa: E402
    child_peak,
    markdown_table,
    median,
    paper_volume_file,
    peak_since,
    round_robin,
    save,
    start_peak,
    warm_up_file,
)
from vtk.util import numpy_support  # noqa: E402

import miss  # noqa: E402
from miss._vtk import to_polydata  # noqa: E402
from miss.geometry import compact  # noqa: E402
from miss.measure._jit import deviation  # noqa: E402
from miss.pipeline import run  # noqa: E402
from miss.spec import JobSpec  # noqa: E402

REDUCE = 0.9
Arrays = tuple[np.ndarray, np.ndarray]
OUT = Path(tempfile.gettempdir()) / "miss-bench-out"

# ----------------------------------------------------------------------------- readers


def read_nibabel(path: Path) -> tuple[np.ndarray, tuple[float, ...]]:
    import nibabel as nib

    img = nib.load(str(path))
    return np.asarray(img.dataobj), tuple(float(z) for z in img.header.get_zooms()[:3])


def read_simpleitk(path: Path) -> tuple[np.ndarray, tuple[float, ...]]:
    import SimpleITK as sitk

    img = sitk.ReadImage(str(path))
    return sitk.GetArrayFromImage(img).T, tuple(img.GetSpacing())  # (z,y,x) C -> (x,y,z) F


def read_vtk(path: Path) -> tuple[np.ndarray, tuple[float, ...]]:
    reader = vtk.vtkNIFTIImageReader()
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    flat = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars())
    return flat.reshape(image.GetDimensions(), order="F"), tuple(image.GetSpacing())


READERS: dict[str, Callable[[Path], tuple[np.ndarray, tuple[float, ...]]]] = {
    "nibabel": read_nibabel,
    "SimpleITK": read_simpleitk,
    "vtkNIFTIImageReader": read_vtk,
}

# ----------------------------------------------------------------------------- surfaces


def _image(data: np.ndarray, spacing: tuple[float, ...]) -> vtk.vtkImageData:
    flat = np.asfortranarray(data).ravel(order="F")
    image = vtk.vtkImageData()
    image.SetDimensions(*data.shape)
    image.SetSpacing(*spacing)
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(flat, deep=False))
    image._keep = flat
    return image


def _poly_arrays(poly: vtk.vtkPolyData) -> Arrays:
    pts = numpy_support.vtk_to_numpy(poly.GetPoints().GetData())
    conn = numpy_support.vtk_to_numpy(poly.GetPolys().GetConnectivityArray())
    return np.array(pts, dtype=np.float32), conn.reshape(-1, 3).astype(np.int32)


def _vtk_contour(
    algorithm: vtk.vtkAlgorithm, data: np.ndarray, spacing: Any, level: float
) -> Arrays:
    algorithm.SetInputData(_image(data, spacing))
    algorithm.SetValue(0, level)
    algorithm.Update()
    return _poly_arrays(algorithm.GetOutput())


def surf_skimage(data: np.ndarray, spacing: Any, level: float) -> Arrays:
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(data, level, spacing=spacing, method="lewiner")
    return verts.astype(np.float32), faces.astype(np.int32)


def surf_zmesh(data: np.ndarray, spacing: Any, level: float) -> Arrays:
    from zmesh import Mesher

    mesher = Mesher(spacing)
    mesher.mesh((data >= level).astype(np.uint8), close=True)
    mesh = mesher.get(1, normals=False)
    return mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32)


SURFACES: dict[str, Callable[[np.ndarray, Any, float], Arrays]] = {
    "skimage marching_cubes (Lewiner)": surf_skimage,
    "VTK flying edges": lambda d, s, lv: _vtk_contour(vtk.vtkFlyingEdges3D(), d, s, lv),
    "VTK marching cubes": lambda d, s, lv: _vtk_contour(vtk.vtkMarchingCubes(), d, s, lv),
    "zmesh (binary labels, no interpolation)": surf_zmesh,
}
#: zmesh meshes a thresholded label volume: a different (blocky) surface, not a contender.
ISOSURFACES = [name for name in SURFACES if not name.startswith("zmesh")]

# ----------------------------------------------------------------------------- decimators


def dec_fast_simplification(v: np.ndarray, f: np.ndarray) -> Arrays:
    import fast_simplification

    pts, tri = fast_simplification.simplify(v, f, target_reduction=REDUCE)
    return pts, tri


def dec_pyfqmr(v: np.ndarray, f: np.ndarray) -> Arrays:
    import pyfqmr

    simplifier = pyfqmr.Simplify()
    simplifier.setMesh(v, f)
    simplifier.simplify_mesh(
        target_count=int(len(f) * (1 - REDUCE)), preserve_border=True, verbose=False
    )
    pts, tri, _ = simplifier.getMesh()
    return pts, tri


def dec_meshoptimizer(v: np.ndarray, f: np.ndarray) -> Arrays:
    import meshoptimizer

    indices = np.ascontiguousarray(f, dtype=np.uint32).ravel()
    out = np.empty_like(indices)
    count = meshoptimizer.simplify(
        out,
        indices,
        np.ascontiguousarray(v, dtype=np.float32),
        target_index_count=int(len(indices) * (1 - REDUCE)) // 3 * 3,
    )
    return compact(v, out[:count].reshape(-1, 3).astype(np.int32))


def _vtk_decimate(algorithm: vtk.vtkAlgorithm, v: np.ndarray, f: np.ndarray) -> Arrays:
    algorithm.SetInputData(to_polydata(v, f))
    algorithm.SetTargetReduction(REDUCE)
    algorithm.Update()
    return _poly_arrays(algorithm.GetOutput())


def dec_miss(method: str) -> Callable[[np.ndarray, np.ndarray], Arrays]:
    def run_miss(v: np.ndarray, f: np.ndarray) -> Arrays:
        out, _ = miss.decimate(miss.Mesh(v, f), method, REDUCE, measure=False, schedule="paper")
        return out.vertices, out.faces

    return run_miss


DECIMATORS: dict[str, Callable[[np.ndarray, np.ndarray], Arrays]] = {
    "fast-simplification": dec_fast_simplification,
    "pyfqmr": dec_pyfqmr,
    "meshoptimizer simplify": dec_meshoptimizer,
    "VTK vtkQuadricDecimation": lambda v, f: _vtk_decimate(vtk.vtkQuadricDecimation(), v, f),
    "VTK vtkDecimatePro": lambda v, f: _vtk_decimate(vtk.vtkDecimatePro(), v, f),
}
SLOW = {"VTK vtkQuadricDecimation", "VTK vtkDecimatePro", "MISS schroeder"}
MISS_DECIMATORS = {"MISS quadric": dec_miss("quadric"), "MISS schroeder": dec_miss("schroeder")}

# ----------------------------------------------------------------------------- writers


def write_trimesh_glb(v: np.ndarray, f: np.ndarray, path: Path) -> int:
    import trimesh

    trimesh.Trimesh(v, f, process=False).export(str(path), file_type="glb")
    return path.stat().st_size


def write_vtk_vrml(v: np.ndarray, f: np.ndarray, path: Path) -> int:
    """VTK's only VRML path is the scene exporter: a mapper, an actor, an off-screen window."""
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputData(to_polydata(v, f))
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    renderer = vtk.vtkRenderer()
    renderer.AddActor(actor)
    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    window.AddRenderer(renderer)
    exporter = vtk.vtkVRMLExporter()
    exporter.SetRenderWindow(window)
    exporter.SetFileName(str(path))
    exporter.Write()
    window.Finalize()
    return path.stat().st_size


def write_miss(fmt: str, **options: Any) -> Callable[[np.ndarray, np.ndarray, Path], int]:
    def write(v: np.ndarray, f: np.ndarray, path: Path) -> int:
        return path.write_bytes(miss.export(miss.Mesh(v, f), fmt, **options))

    return write


GLB_WRITERS = {"trimesh GLB": write_trimesh_glb}
VRML_WRITERS = {"VTK vtkVRMLExporter": write_vtk_vrml}
MISS_WRITERS = {
    "MISS GLB": write_miss("glb"),
    "MISS GLB compress=True": write_miss("glb", compress=True),
    "MISS VRML": write_miss("wrl"),
}

# ----------------------------------------------------------------------------- stages


def bench_readers(path: Path, repeats: int) -> dict[str, float]:
    seconds, _ = round_robin(
        {name: (lambda fn=fn: fn(path)) for name, fn in READERS.items()}, repeats
    )
    seconds["MISS load_volume"] = round_robin({"m": lambda: miss.load_volume(path)}, repeats)[0][
        "m"
    ]
    return {name: median(s) for name, s in seconds.items()}


def bench_surfaces(data: np.ndarray, spacing: Any, level: float, repeats: int) -> dict[str, Any]:
    volume = miss.Volume(np.asfortranarray(data), np.diag([*spacing, 1.0]))
    runs = {name: (lambda fn=fn: fn(data, spacing, level)) for name, fn in SURFACES.items()}
    runs["MISS extract_surface"] = lambda: _arrays(miss.extract_surface(volume, level))
    seconds, last = round_robin(runs, repeats)
    return {
        name: {"seconds": median(s), "triangles": len(last[name][1]), "mesh": last[name]}
        for name, s in seconds.items()
    }


def _arrays(mesh: miss.Mesh) -> Arrays:
    return mesh.vertices, mesh.faces


def bench_decimators(surface: Arrays, repeats: int, slow_repeats: int) -> dict[str, Any]:
    """Every decimator on the same surface; the slow VTK ones run fewer times."""
    everyone = {**DECIMATORS, **MISS_DECIMATORS}
    v, f = surface
    fast = {n: (lambda fn=fn: fn(v, f)) for n, fn in everyone.items() if n not in SLOW}
    slow = {n: (lambda fn=fn: fn(v, f)) for n, fn in everyone.items() if n in SLOW}
    seconds, last = round_robin(fast, repeats)
    slow_seconds, slow_last = round_robin(slow, slow_repeats)
    seconds.update(slow_seconds)
    last.update(slow_last)
    source = miss.Mesh(v, f)
    out = {}
    for name in everyone:
        dv, df = last[name]
        dev = deviation(source, miss.Mesh(np.asarray(dv, np.float32), np.asarray(df, np.int32)))
        out[name] = {
            "seconds": median(seconds[name]),
            "runs": len(seconds[name]),
            "triangles": len(df),
            "reduction": 1 - len(df) / len(f),
            "max_error_mm": dev.max_mm,
            "mean_error_mm": dev.mean_mm,
        }
    return out


def bench_writers(mesh: Arrays, repeats: int) -> dict[str, Any]:
    OUT.mkdir(parents=True, exist_ok=True)
    writers = {**GLB_WRITERS, **VRML_WRITERS, **MISS_WRITERS}
    runs = {n: (lambda n=n, w=w: w(*mesh, OUT / f"w-{abs(hash(n))}")) for n, w in writers.items()}
    seconds, last = round_robin(runs, repeats)
    n_tri = len(mesh[1])
    return {
        n: {"seconds": median(seconds[n]), "bytes": last[n], "bytes_per_triangle": last[n] / n_tri}
        for n in writers
    }


# ----------------------------------------------------------------------------- whole jobs


def peer_job(chain: dict[str, str], path: Path, level: float) -> dict[str, Any]:
    """Read, surface, decimate, write GLB and VRML with the named peer of each stage."""
    t0 = time.perf_counter()
    data, spacing = READERS[chain["read"]](path)
    surface = SURFACES[chain["surface"]](data, spacing, level)
    del data
    final = DECIMATORS[chain["decimate"]](*surface)
    sizes = [
        GLB_WRITERS[chain["glb"]](*final, OUT / "peer.glb"),
        VRML_WRITERS[chain["vrml"]](*final, OUT / "peer.wrl"),
    ]
    return {
        "seconds": time.perf_counter() - t0,
        "surface": surface,
        "final": final,
        "bytes": sum(sizes),
    }


def miss_api_job(path: Path, level: float) -> dict[str, Any]:
    """MISS through its public functions, measurement off like the peers."""
    t0 = time.perf_counter()
    volume = miss.load_volume(path)
    surface = miss.extract_surface(volume, level, normals=False)  # decimate makes new ones
    del volume
    final, _ = miss.decimate(surface, "quadric", REDUCE, measure=False, schedule="paper")
    sizes = [
        (OUT / "miss.glb").write_bytes(miss.export(final, "glb")),
        (OUT / "miss.wrl").write_bytes(miss.export(final, "wrl")),
    ]
    return {
        "seconds": time.perf_counter() - t0,
        "surface": _arrays(surface),
        "final": _arrays(final),
        "bytes": sum(sizes),
    }


def miss_pipeline_job(path: Path, level: float) -> dict[str, Any]:
    """``miss.pipeline.run``: the web system's job, which also measures its deviation."""
    t0 = time.perf_counter()
    spec = JobSpec.of(
        level=level, formats=("glb", "wrl"), schedule="paper"
    )  # to 10 %, as the peers
    result = run(miss.load_volume(path), spec)
    sizes = [(OUT / f"pipe.{fmt}").write_bytes(data) for fmt, data in result.artifacts.items()]
    return {
        "seconds": time.perf_counter() - t0,
        "surface": None,
        "final": _arrays(result.mesh),
        "bytes": sum(sizes),
        "report": result.report,
    }


def job_runner(name: str, chain: dict[str, str], path: Path, level: float) -> Callable[[], Any]:
    if name == "MISS public API":
        return lambda: miss_api_job(path, level)
    if name == "MISS pipeline.run (measures)":
        return lambda: miss_pipeline_job(path, level)
    return lambda: peer_job(chain, path, level)


def best_chain(stages: dict[str, Any]) -> dict[str, str]:
    """The fastest peer of each stage; a decimator must reach at least 85 % reduction."""
    readers = {k: v for k, v in stages["read"].items() if not k.startswith("MISS")}
    decimators = {
        k: v for k, v in stages["decimate"].items() if k in DECIMATORS and v["reduction"] >= 0.85
    }
    return {
        "read": min(readers, key=readers.get),
        "surface": min(ISOSURFACES, key=lambda k: stages["surface"][k]["seconds"]),
        "decimate": min(decimators, key=lambda k: decimators[k]["seconds"]),
        "glb": min(GLB_WRITERS, key=lambda k: stages["write"][k]["seconds"]),
        "vrml": min(VRML_WRITERS, key=lambda k: stages["write"][k]["seconds"]),
    }


JOBS = ("best composed peer pipeline", "MISS public API", "MISS pipeline.run (measures)")


def bench_jobs(chain: dict[str, str], path: Path, level: float, repeats: int) -> dict[str, Any]:
    OUT.mkdir(parents=True, exist_ok=True)
    runs = {name: job_runner(name, chain, path, level) for name in JOBS}
    for fn in runs.values():
        fn()  # warm: first-use costs (imports, EGL context, numba) are not the job's
    cpu: dict[str, list[float]] = {}
    seconds, last = round_robin(runs, repeats, cpu)
    miss_surface = miss.extract_surface(miss.load_volume(path), level)
    out = {}
    for name in JOBS:
        surface = last[name]["surface"] or _arrays(miss_surface)
        final = last[name]["final"]
        dev = deviation(
            miss.Mesh(*surface),
            miss.Mesh(np.asarray(final[0], np.float32), np.asarray(final[1], np.int32)),
        )
        out[name] = {
            "seconds": median(seconds[name]),
            "cpu_seconds": median(cpu[name]),
            "runs": seconds[name],
            "triangles": len(final[1]),
            "bytes": last[name]["bytes"],
            "max_error_mm": dev.max_mm,
            "mean_error_mm": dev.mean_mm,
        }
    return out


# ----------------------------------------------------------------------------- peak memory


def child(args: list[str]) -> None:
    """In a fresh process: warm up on a small file, then one job; print its peak as JSON."""
    name, path, level, chain = (
        args[0],
        Path(args[1]),
        float(args[2]),
        dict(zip(("read", "surface", "decimate", "glb", "vrml"), args[3:], strict=False)),
    )
    OUT.mkdir(parents=True, exist_ok=True)
    job_runner(name, chain, warm_up_file(), 300.0)()  # the phantom's bone level, in HU
    baseline = start_peak()
    result = job_runner(name, chain, path, level)()
    import json

    print(
        json.dumps(
            {
                "peak_bytes": peak_since(baseline),
                "output_bytes": result["bytes"],
                "seconds": result["seconds"],
            }
        )
    )


def bench_memory(
    chain: dict[str, str], path: Path, level: float, volume_bytes: int
) -> dict[str, Any]:
    out = {}
    for name in JOBS:
        res = child_peak(Path(__file__), [name, str(path), str(level), *chain.values()])
        res["budget_bytes"] = 3 * volume_bytes + res["output_bytes"]
        res["peak_over_volume"] = res["peak_bytes"] / volume_bytes
        res["within_budget"] = res["peak_bytes"] <= res["budget_bytes"]
        out[name] = res
    return out


# ----------------------------------------------------------------------------- report


STAGE_COLUMNS = {
    "read": ["reader", "seconds"],
    "surface": ["method", "seconds", "triangles"],
    "decimate": [
        "method",
        "seconds",
        "runs",
        "triangles",
        "removed",
        "max error mm",
        "mean error mm",
    ],
    "write": ["writer", "seconds", "bytes", "bytes/triangle"],
}
JOB_COLUMNS = [
    "job",
    "seconds",
    "CPU seconds",
    "speed-up vs best peer",
    "triangles",
    "max error mm",
    "mean error mm",
    "peak MB",
    "peak / volume bytes",
    "<= 3x volume + output",
]


def _stage_row(stage: str, name: str, v: Any) -> list[Any]:
    if stage == "read":
        return [name, v]
    if stage == "surface":
        return [name, v["seconds"], v["triangles"]]
    if stage == "decimate":
        return [
            name,
            v["seconds"],
            v["runs"],
            v["triangles"],
            f"{v['reduction']:.1%}",
            v["max_error_mm"],
            v["mean_error_mm"],
        ]
    return [name, v["seconds"], v["bytes"], v["bytes_per_triangle"]]


def _job_rows(res: dict[str, Any]) -> list[list[Any]]:
    best = res["jobs"]["best composed peer pipeline"]["seconds"]
    rows = []
    for name, j in res["jobs"].items():
        m = res["memory"][name]
        rows.append(
            [
                name,
                j["seconds"],
                j["cpu_seconds"],
                best / j["seconds"],
                j["triangles"],
                j["max_error_mm"],
                j["mean_error_mm"],
                m["peak_bytes"] / 2**20,
                m["peak_over_volume"],
                "yes" if m["within_budget"] else "no",
            ]
        )
    return rows


def report(res: dict[str, Any]) -> str:
    """The Markdown tables of one run."""
    titles = {
        "read": "**Read**",
        "surface": "**Isosurface**",
        "decimate": "**Decimate to 10 %** (input: MISS's surface, closed)",
        "write": "**Write** (the decimated mesh)",
    }
    parts = [
        f"Volume {res['volume']}, level {res['level']:g}; medians of {res['repeats']} runs "
        f"(slow VTK decimators and MISS schroeder: {res['slow_repeats']}).\n"
    ]
    for stage, columns in STAGE_COLUMNS.items():
        rows = [_stage_row(stage, k, v) for k, v in res["stages"][stage].items()]
        parts.append(f"\n{titles[stage]}\n\n" + markdown_table(columns, rows))
    chain = " + ".join(res["chain"].values())
    parts.append(
        f"\n**Whole job** (best composed peer pipeline: {chain})\n\n"
        + markdown_table(JOB_COLUMNS, _job_rows(res))
    )
    return "".join(parts)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--slow-repeats", type=int, default=1)
    parser.add_argument("--level", type=float, default=1500.0)
    args = parser.parse_args(argv)
    path = paper_volume_file()
    data, spacing = read_nibabel(path)
    res: dict[str, Any] = {
        "volume": "CThead 256x256x225 int16",
        "level": args.level,
        "repeats": args.repeats,
        "slow_repeats": args.slow_repeats,
        "stages": {},
    }
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    res["stages"]["read"] = bench_readers(path, args.repeats)
    log("read done")
    surfaces = bench_surfaces(data, spacing, args.level, args.repeats)
    # MISS's surface is the decimators' common input: VTK's quadric decimation gives up
    # (0 % removed) on flying edges' raw output at a whole-number level, whose voxels equal
    # to the level make zero-area triangles; MISS contours a quarter level below (same
    # inside/outside, no degenerate triangles)
    source = surfaces["MISS extract_surface"].pop("mesh")
    for v in surfaces.values():
        v.pop("mesh", None)
    res["stages"]["surface"] = surfaces
    log("surface done")
    res["stages"]["decimate"] = bench_decimators(source, args.repeats, args.slow_repeats)
    log("decimate done")
    res["stages"]["write"] = bench_writers(dec_meshoptimizer(*source), args.repeats)
    res["chain"] = best_chain(res["stages"])
    res["jobs"] = bench_jobs(res["chain"], path, args.level, args.repeats)
    log("jobs done")
    res["memory"] = bench_memory(res["chain"], path, args.level, int(data.nbytes))
    table = report(res)
    save("peers", res, table)
    print(table)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2:])
    else:
        main()
