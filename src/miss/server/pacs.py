"""The PACS in the server: imports (a series becomes a MISS volume) and sends (a model goes
back into the patient's study as Encapsulated STL).

An import is a small job of its own, run on a thread (:class:`PacsImports`): it lists the
series' instances, retrieves them into a private folder under ``tmp/``, and hands that
folder to :func:`miss.server.ingest.ingest`, the same door an upload goes through: the
confined reader, the same checks and messages, de-identification, the original identity
kept for the owner only (with where it came from: the PACS, the original study, series
and image UIDs, so the model can be sent back). A DICOM SEG or RT-STRUCT of the same
study that refers to the series becomes the volume's label map.
"""

from __future__ import annotations

import io
import json
import logging
import shutil
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from miss import __version__
from miss.errors import BadParameter, MissError
from miss.pacs import client
from miss.pacs.server import PacsServer
from miss.pacs.stl import Origin, encapsulate
from miss.server import audit
from miss.server.accounts import User
from miss.server.errors import NotFound, NotReady
from miss.server.ingest import Reading, ingest
from miss.server.settings import Settings
from miss.server.storage.db import (
    DONE,
    FAILED,
    QUEUED,
    RUNNING,
    ModelRow,
    PacsImportRow,
    VolumeRow,
    utcnow,
)
from miss.server.storage.store import Store, new_id
from miss.server.uploads import Upload

log = logging.getLogger("miss.server")

#: Most instances one imported series may have (slices; a multi-frame file counts once).
MAX_INSTANCES = 5000
#: Largest DICOM SEG or RT-STRUCT series retrieved (an uncompressed SEG of a 20-slice CT
#: with 31 segments is 17 MB).
MAX_SEGMENTATION_BYTES = 1 << 30
RESTARTED = "the server restarted during the import; import the series again."


def fail_interrupted(store: Store) -> None:
    """Imports that were under way when the server stopped failed: say so. Only a server
    that starts alone calls it (its files in ``tmp/`` are swept at the same time); one that
    starts beside others on PostgreSQL leaves their imports be."""
    with store.session.begin() as s:
        s.execute(
            update(PacsImportRow)
            .where(PacsImportRow.status.in_((QUEUED, RUNNING)))
            .values(status=FAILED, error=RESTARTED, finished_at=utcnow())
        )


class PacsImports:
    """Imports run on ``settings.pacs_imports`` threads; each is a row in ``pacs_imports``
    that its owner polls (``GET /api/pacs/imports/{id}``)."""

    def __init__(self, store: Store, settings: Settings, reading: Callable[[], Reading]) -> None:
        self.store, self.settings, self.reading = store, settings, reading
        self.pool = ThreadPoolExecutor(settings.pacs_imports, thread_name_prefix="miss-pacs")

    def stop(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)

    def submit(
        self, user: User, server: PacsServer, study: str, series: str, segmentation: str
    ) -> PacsImportRow:
        row = PacsImportRow(
            id=new_id(), owner_id=user.id, pacs=server.name, study=study, series=series,
            segmentation=segmentation,
        )  # fmt: skip
        with self.store.session.begin() as s:
            s.add(row)
        self.pool.submit(self._run, row.id, user, server)
        return row

    def get(self, import_id: str, user: User) -> PacsImportRow:
        with self.store.session() as s:
            row = s.get(PacsImportRow, import_id)
        if row is None or row.owner_id != user.id:
            raise NotFound(f"no import {import_id!r}; GET /api/pacs/imports lists yours.")
        return row

    def list(self, user: User, limit: int = 50) -> list[PacsImportRow]:
        with self.store.session() as s:
            query = (
                select(PacsImportRow)
                .where(PacsImportRow.owner_id == user.id)
                .order_by(PacsImportRow.created_at.desc())
                .limit(limit)
            )
            return list(s.scalars(query))

    def _set(self, import_id: str, **values: Any) -> None:
        with self.store.session.begin() as s:
            s.execute(update(PacsImportRow).where(PacsImportRow.id == import_id).values(**values))

    def _run(self, import_id: str, user: User, server: PacsServer) -> None:
        row = self.get(import_id, user)
        self._set(import_id, status=RUNNING, stage="listing the series", progress=0.02)
        work: Path | None = None
        try:
            self.store.check_free_space(self.settings.min_free_bytes)
            work = self.store.tmp_dir()
            volume, labels = self._import(row, user, server, work)
        except MissError as exc:
            self._set(import_id, status=FAILED, error=str(exc), finished_at=utcnow())
            audit.record(self.store, "pacs_import_failed", user.name, import_id, pacs=server.name)
            return
        except Exception as exc:  # a bug: the import fails, the server goes on
            log.exception("PACS import %s failed", import_id)
            error = f"internal error ({type(exc).__name__}); see the server's log."
            self._set(import_id, status=FAILED, error=error, finished_at=utcnow())
            return
        finally:
            if work is not None:
                shutil.rmtree(work, ignore_errors=True)
        self._set(
            import_id, status=DONE, stage="done", progress=1.0, volume_id=volume.id,
            labels=labels, name=volume.name, finished_at=utcnow(),
        )  # fmt: skip
        audit.record(
            self.store, "pacs_import", user.name, volume.id, pacs=server.name, labels=labels
        )

    def _import(
        self, row: PacsImportRow, user: User, server: PacsServer, work: Path
    ) -> tuple[VolumeRow, int]:
        instances = client.list_instances(server, row.study, row.series, MAX_INSTANCES)
        found = work / "unzipped"
        found.mkdir()
        total = len(instances)

        def retrieved(n: int) -> None:
            self._set(row.id, stage=f"retrieving {n} of {total}", progress=0.05 + 0.6 * n / total)

        with self.store.disk_full_as_507():
            client.retrieve_series(
                server, row.study, row.series, found, self.settings.max_upload_bytes, total,
                retrieved,
            )  # fmt: skip
        self._set(row.id, stage="reading the images", progress=0.7)
        listed = client.search_series(server, row.study)  # the study's series, asked once
        described = next((r for r in listed if r["series"] == row.series), {})
        name = " ".join(x for x in (described.get("modality"), described.get("description")) if x)
        upload = Upload(path=work / "pacs-series", filename=name, fields={"name": name or "PACS"})
        origin = {
            "pacs": server.name,
            "study": row.study,
            "series": row.series,
            "instances": [list(i) for i in instances],
        }
        volume = ingest(self.store, upload, work, self.reading(), user.id, origin)
        labels = 0
        if row.segmentation != "none":
            self._set(row.id, stage="looking for segmentations", progress=0.9)
            try:
                labels = self._segmentation(row, server, volume, work, listed)
            except MissError as exc:  # the images are in: keep them, say what was not
                error = f"the series was imported, its segmentation was not: {exc}"
                self._set(row.id, error=error)
        return volume, labels

    def _segmentation(
        self,
        row: PacsImportRow,
        server: PacsServer,
        volume: VolumeRow,
        work: Path,
        listed: list[dict[str, Any]],
    ) -> int:
        """Lay the study's SEG or RT-STRUCT of this series over the volume; its label
        count (0: none found)."""
        from miss.server import labelmaps

        found = find_segmentation(server, row.study, row.series, row.segmentation, work, listed)
        if found is None:
            return 0
        scan = self.store.open_volume(volume.id)
        labels, meta = labelmaps.read_segmentation(found, scan, work, self.reading())
        labelmaps.save(self.store, volume.id, labels, meta)
        return len(meta["labels"])


def find_segmentation(
    server: PacsServer,
    study: str,
    series: str,
    wanted: str,
    work: Path,
    rows: list[dict[str, Any]],
) -> Path | None:
    """Retrieve the SEG or RT-STRUCT series ``wanted`` (a UID), or with ``auto`` the newest
    one in ``study`` that refers to ``series``, into ``work/unzipped/`` (where the confined
    reader looks); None when none does. ``rows``: the study's series
    (:func:`miss.pacs.client.search_series`)."""
    if wanted != "auto":
        rows = [r for r in rows if r["series"] == wanted]
        if not rows or not rows[0]["segmentation"]:
            raise BadParameter(
                f"series {wanted} of the study is not a DICOM SEG or RT-STRUCT; pick one "
                "from GET /api/pacs/studies/{study}/series, or send segmentation 'none'."
            )
    folder = work / "unzipped"
    for candidate in reversed([r for r in rows if r["segmentation"]]):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        client.retrieve_series(
            server, study, candidate["series"], folder, MAX_SEGMENTATION_BYTES,
            candidate["instances"] or 64, images=False,
        )  # fmt: skip
        if wanted != "auto" or refers_to(folder, series):
            return folder
    return None


def refers_to(folder: Path, series: str) -> bool:
    """Whether the SEG or RT-STRUCT in ``folder`` names ``series`` as its source."""
    import pydicom

    for path in sorted(folder.glob("*.dcm")):
        ds = pydicom.dcmread(path, stop_before_pixels=True)
        for item in ds.get("ReferencedSeriesSequence") or []:
            if str(item.get("SeriesInstanceUID", "")) == series:
                return True
        for frame in ds.get("ReferencedFrameOfReferenceSequence") or []:
            for study in frame.get("RTReferencedStudySequence") or []:
                for item in study.get("RTReferencedSeriesSequence") or []:
                    if str(item.get("SeriesInstanceUID", "")) == series:
                        return True
    return False


# ---------------------------------------------------------------- sending


def origin_of(store: Store, volume: VolumeRow) -> Origin:
    """The original study, series, frame of reference and patient of ``volume`` (from its
    owner-only identity record); BadParameter for a volume that did not come from DICOM."""
    record = store.get_identity(volume.id)
    data = record.data if record else {}
    back = {new: old for old, new in (data.get("uids") or {}).items()}
    study = back.get(volume.info.get("study_uid") or "")
    if not study:
        raise BadParameter(
            "this volume has no DICOM study to send a model into (it was not read from a "
            "DICOM series); import the series from the PACS and model it there."
        )
    came = data.get("origin") or {}
    return Origin(
        study=study,
        series=back.get(volume.info.get("series_uid") or "", came.get("series", "")),
        frame_of_reference=back.get(volume.info.get("frame_of_reference") or "", ""),
        patient={k: str(v) for k, v in (data.get("patient") or {}).items()},
        sources=[tuple(i) for i in came.get("instances") or []],  # type: ignore[misc]
    )


def stl_parts(folder: Path) -> list[tuple[str, bytes]]:
    """(part name, STL bytes) of a finished model: ``model.stl`` is one STL, or a zip with
    one STL a part and ``scene.json``."""
    data = (folder / "model.stl").read_bytes()
    if not data.startswith(b"PK\x03\x04"):
        return [("", data)]
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        scene = json.loads(archive.read("scene.json"))
        return [(p.get("name", ""), archive.read(p["file"])) for p in scene["parts"]]


def describe(model: ModelRow, volume: VolumeRow) -> str:
    """The new series' description: ``MISS surface: bone 300 HU, 90 % decimated``."""
    stats = model.stats or {}
    parts = [p.get("name") or "surface" for p in stats.get("parts") or []]
    level, units = (model.spec or {}).get("level"), volume.info.get("units") or ""
    if len(parts) == 1 and level is not None and f"{level:g}" not in parts[0]:
        what = f"{parts[0]} {level:g} {units}".strip()
    elif len(parts) == 1:
        what = parts[0]  # the default name says its level: "bone (300 HU)"
    else:
        what = f"{len(parts)} structures"
    decimation = stats.get("decimation") or {}
    if decimation.get("method", "none") == "none":
        return f"MISS surface: {what}, not decimated"
    return (
        f"MISS surface: {what}, {round(100 * decimation.get('achieved_reduction', 0))} % decimated"
    )


def send_model(
    store: Store, server: PacsServer, model: ModelRow, volume: VolumeRow, user: User
) -> dict[str, Any]:
    """Send a finished model into its volume's original study on ``server`` as one
    Encapsulated STL instance a part, in a new series; what was stored."""
    if volume.owner_id != user.id:
        raise NotFound(f"no model {model.id!r} of yours; only a volume's owner sends its models.")
    if model.status != DONE:
        raise NotReady(f"model {model.id!r} is {model.status}; send it once it is done.")
    origin = origin_of(store, volume)
    parts = stl_parts(store.model_dir(model.id))
    description = describe(model, volume)
    titles = [p.get("name", "") for p in (model.stats or {}).get("parts") or []]
    named = [(title or name or description, stl) for (name, stl), title in _pad(parts, titles)]
    datasets = encapsulate(named, origin, description, f"MISS {__version__}")
    stored = client.store(server, datasets, origin.study)
    return {
        "pacs": server.name,
        "series_uid": str(datasets[0].SeriesInstanceUID),
        "sop_instance_uids": stored,
        "description": description,
        "parts": [title for title, _ in named],
    }


def _pad(parts: list[tuple[str, bytes]], titles: list[str]) -> list[tuple[tuple[str, bytes], str]]:
    return [(part, titles[i] if i < len(titles) else "") for i, part in enumerate(parts)]
