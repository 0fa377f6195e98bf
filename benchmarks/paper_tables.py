"""The paper's Tables 1-2 regenerated, plus a picture of the two levels.

    .venv/bin/python benchmarks/paper_tables.py [--repeats 5] [--sample-rates 1,2,4]
                                                [--volume CThead.nhdr] [--out DIR] [--render]
                                                [--schedule both|paper|guaranteed]

Writes ``results/paper_tables.{json,md,png}`` (the paper's schedule),
``results/paper_tables_guaranteed.*`` (bounds held as caps) and, for both,
``results/paper_tables_both.md`` (the decimated rows side by side); ``--render`` also draws the skin (600) and
bone (1500) surfaces of the paper volume side by side, ``results/levels_600_1500.png``, the
visual check that 600 is the skin in CThead's units.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import paper as bench

import miss
from miss._vtk import to_polydata

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per row (median)")
    parser.add_argument("--out", default=str(RESULTS), help="folder for JSON, Markdown, PNG")
    parser.add_argument("--volume", default=None, help="CThead.nhdr (default: ../shared)")
    parser.add_argument("--sample-rates", default="1,2,4", metavar="A,B,...")
    parser.add_argument("--render", action="store_true", help="also draw the two levels")
    parser.add_argument("--schedule", choices=("both", *bench.SCHEDULES), default="both")
    args = parser.parse_args(argv)
    try:
        rates = tuple(int(r) for r in args.sample_rates.split(","))
    except ValueError:
        print(
            f"--sample-rates must be integers like 1,2,4, got {args.sample_rates!r}",
            file=sys.stderr,
        )
        return 2
    out = Path(args.out)
    volume = Path(args.volume) if args.volume else None
    log = lambda line: print(line, file=sys.stderr)  # noqa: E731
    schedules = bench.SCHEDULES if args.schedule == "both" else (args.schedule,)
    rows = {}
    for schedule in schedules:
        result = bench.run_paper(out, args.repeats, volume, rates, log=log, schedule=schedule)
        rows[schedule] = bench.rows_from_json(result)
        print(f"schedule {schedule}\n\n" + bench.markdown(rows[schedule]))
    if len(rows) == 2:
        both = bench.side_by_side(rows["paper"], rows["guaranteed"])
        (out / "paper_tables_both.md").write_text(both)
        print(both)
    print(f"wrote {out / 'paper_tables*.json'}, .md and .png")
    if args.render:
        render_levels(bench.paper_volume(), out / "levels_600_1500.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
