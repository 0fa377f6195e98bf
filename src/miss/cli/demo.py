"""``miss demo``: the synthetic CT head phantom, a volume with no patient in it."""

from __future__ import annotations

import argparse


def add_arguments(demo: argparse.ArgumentParser) -> None:
    """``miss demo``: the NIfTI file to write."""
    demo.add_argument("output", help="e.g. demo-head.nii.gz")


def cmd_demo(args: argparse.Namespace) -> int:
    """Write the CT head phantom (HU) as a NIfTI file; the exit status."""
    import nibabel as nib
    import numpy as np

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
