"""The job ``miss convert`` does, composed from today's peers as a user would write it.

    python benchmarks/peer_script.py VOLUME.nii OUT.glb OUT.wrl [LEVEL] [REDUCE]

nibabel reads the NIfTI; VTK's flying edges makes the isosurface (on both cores, as MISS
runs it); meshoptimizer simplifies it to 10 % of its triangles (with the error cap MISS
uses, 1 % of the mesh's extent); trimesh writes the GLB and a few lines the VRML
IndexedFaceSet. Vertices are in LPS mm from the NIfTI affine, as MISS gives them.
"""

import os
import sys

os.environ.setdefault("VTK_SMP_BACKEND_IN_USE", "STDThread")

import meshoptimizer  # noqa: E402
import nibabel as nib  # noqa: E402
import numpy as np  # noqa: E402
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy  # noqa: E402
from vtkmodules.vtkCommonDataModel import vtkImageData  # noqa: E402
from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D  # noqa: E402


def isosurface(path: str, level: float) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float32 LPS mm, faces (F, 3) uint32) of the volume at ``level``."""
    img = nib.load(path)
    image = vtkImageData()
    image.SetDimensions(*img.shape[:3])
    voxels = np.asarray(img.dataobj).ravel(order="F")
    image.GetPointData().SetScalars(numpy_to_vtk(voxels, deep=False))
    edges = vtkFlyingEdges3D()
    edges.SetInputData(image)
    edges.SetValue(0, level)
    edges.ComputeNormalsOff()  # the simplification would throw them away
    edges.Update()
    index_xyz = vtk_to_numpy(edges.GetOutput().GetPoints().GetData())
    faces = vtk_to_numpy(edges.GetOutput().GetPolys().GetConnectivityArray())
    lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ img.affine  # NIfTI is RAS, MISS gives LPS
    points = (index_xyz @ lps[:3, :3].T + lps[:3, 3]).astype(np.float32)
    return points, faces.astype(np.uint32).reshape(-1, 3)


def main(source: str, glb: str, wrl: str, level: float = 1500.0, reduce: float = 0.9) -> None:
    import trimesh

    points, faces = isosurface(source, level)
    kept = np.empty(faces.size, dtype=np.uint32)
    target = int(faces.size * (1 - reduce)) // 3 * 3
    count = meshoptimizer.simplify(kept, faces.ravel(), points, target_index_count=target)
    used, tri = np.unique(kept[:count], return_inverse=True)  # drop the unused vertices
    mesh = trimesh.Trimesh(points[used], tri.reshape(-1, 3), process=False)
    mesh.export(glb)
    with open(wrl, "w") as out:
        out.write("#VRML V2.0 utf8\nShape { geometry IndexedFaceSet { coord Coordinate { point [\n")
        out.write(",\n".join(f"{x:.3f} {y:.3f} {z:.3f}" for x, y, z in mesh.vertices.tolist()))
        out.write("] }\ncoordIndex [\n")
        out.write(",\n".join(f"{a},{b},{c},-1" for a, b, c in mesh.faces.tolist()))
        out.write("] } }\n")


if __name__ == "__main__":
    main(*sys.argv[1:4], *(float(a) for a in sys.argv[4:6]))
