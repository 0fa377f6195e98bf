"""The paper's Tables 1-2 (same as ``miss bench paper``), plus a picture of the two levels.

    .venv/bin/python benchmarks/paper_tables.py [--repeats 5] [--render]

Writes ``results/paper_tables.{json,md,png}``; ``--render`` also draws the skin (600) and
bone (1500) surfaces of the paper volume side by side, ``results/levels_600_1500.png``, the
visual check that 600 is the skin in CThead's units.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import miss
from miss import bench
from miss.deviation import to_polydata

RESULTS = Path(__file__).resolve().parent / "results"


def render_levels(volume: miss.Volume, path: Path) -> None:
    """Off-screen VTK rendering of the skin and bone surfaces (sample rate 2), seen from the
    front (LPS: the camera on -y, superior up)."""
    import vtk

    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    window.SetSize(900, 450)
    for i, (tissue, colour) in enumerate(
        (("skin", (0.9, 0.75, 0.65)), ("bone", (0.95, 0.93, 0.85)))
    ):
        mesh = miss.extract_surface(volume, bench.LEVELS[tissue], sample_rate=2)
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputData(to_polydata(mesh.vertices, mesh.faces))
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().SetColor(*colour)
        renderer = vtk.vtkRenderer()
        renderer.SetViewport(i * 0.5, 0, (i + 1) * 0.5, 1)
        renderer.AddActor(actor)
        renderer.SetBackground(0.1, 0.1, 0.15)
        camera = renderer.GetActiveCamera()
        camera.SetPosition(0, -1, 0)
        camera.SetViewUp(0, 0, -1)  # CThead's slice 1 is the vertex: +z runs down the head
        renderer.ResetCamera()
        window.AddRenderer(renderer)
    window.Render()
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(window)
    writer = vtk.vtkPNGWriter()
    writer.SetFileName(str(path))
    writer.SetInputConnection(grab.GetOutputPort())
    writer.Write()
    window.Finalize()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--render", action="store_true", help="also draw the two levels")
    args = parser.parse_args()
    result = bench.run_paper(RESULTS, args.repeats, log=lambda line: print(line, file=sys.stderr))
    print(bench.markdown(bench.rows_from_json(result)))
    if args.render:
        render_levels(bench.paper_volume(), RESULTS / "levels_600_1500.png")


if __name__ == "__main__":
    main()
