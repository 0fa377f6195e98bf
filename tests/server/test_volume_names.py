"""A scan uploaded without a name is named by what it says of itself; one whose file
gives no modality (NIfTI, NRRD, MetaImage) by its format, as the library shows it, never
"Scan"."""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
from fastapi.testclient import TestClient


def test_a_nifti_without_modality_is_named_by_its_format(client: TestClient, upload_for) -> None:
    data = np.zeros((16, 16, 16), np.int16)
    data[4:12, 4:12, 4:12] = 200  # nothing like CT's air: no modality
    content = gzip.compress(nib.Nifti1Image(data, np.eye(4)).to_bytes())
    volume = upload_for(client, {}, content, "scan.nii.gz")
    assert volume["modality"] == "" and volume["source_format"] == "nifti"
    assert volume["name"].startswith("NIfTI volume, uploaded "), volume["name"]
