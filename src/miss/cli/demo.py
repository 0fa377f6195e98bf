"""``miss demo`` (the synthetic CT head phantom) and ``miss bench paper``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np


def add_parsers(sub: Any) -> None:
    demo = sub.add_parser("demo", help="write the synthetic CT head phantom as NIfTI")
    demo.add_argument("output", help="e.g. demo-head.nii.gz")

    bench = sub.add_parser("bench", help="regenerate the 1998 paper's performance tables")
    bench.add_argument("suite", choices=["paper"], help="'paper': Tables 1-2 on the CThead volume")
    bench.add_argument(
        "--out", default="benchmarks/results", help="folder for JSON, Markdown and PNG"
    )
    bench.add_argument(
        "--repeats", type=int, default=5, help="timed runs per row (the median is kept)"
    )
    bench.add_argument("--volume", default=None, help="CThead.nhdr (default: ../shared/datasets)")
    bench.add_argument(
        "--sample-rates",
        default="1,2,4",
        metavar="A,B,...",
        help="sample rates to measure (default 1,2,4)",
    )


def cmd_demo(args: argparse.Namespace) -> int:
    import nibabel as nib

    from miss.demo import phantom

    vol = phantom()
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ vol.affine  # NIfTI stores RAS
    image = nib.Nifti1Image(np.asarray(vol.data), ras)
    image.header.set_xyzt_units("mm")
    image.header["descrip"] = b"MISS CT phantom HU"
    nib.save(image, args.output)
    print(
        f"wrote {args.output}: {' x '.join(map(str, vol.dims))} voxels, HU (bone ~300, skin ~-500)"
    )
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from miss import bench
    from miss.errors import BadParameter

    try:
        rates = tuple(int(r) for r in args.sample_rates.split(","))
    except ValueError:
        raise BadParameter(
            f"--sample-rates must be integers like 1,2,4, got {args.sample_rates!r}"
        ) from None
    out = Path(args.out)
    result = bench.run_paper(
        out,
        args.repeats,
        Path(args.volume) if args.volume else None,
        rates,
        log=lambda line: print(line, file=sys.stderr),
    )
    print(bench.markdown(bench.rows_from_json(result)))
    print(f"wrote {out / 'paper_tables.json'}, .md and .png")
    return 0
