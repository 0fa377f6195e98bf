"""The PACS in the server: imports (a series becomes a MISS volume) and sends (a model goes
back into the patient's study as Encapsulated STL).

An import is a small job of its own, run on a thread (:class:`PacsImports`): it lists the
series' instances, retrieves them into a private folder under ``tmp/``, and hands that
folder to :func:`miss.server.volumes.ingest.ingest`, the same door an upload goes through: the
confined reader, the same checks and messages, de-identification, the original identity
kept for the owner only (with where it came from: the PACS, the original study, series
and image UIDs and the study's patient ID as the PACS has it, so the model can be sent
back). A DICOM SEG or RT-STRUCT of the same study that refers to the series becomes the
volume's label map.

A model goes back only into the study its volume was imported from, on that PACS, and
only after the PACS confirms that the study still has that patient ID and source series
(:func:`destination`); a file someone uploaded may carry any study UID and patient, so
an uploaded volume's model goes, if ``MISS_PACS_SEND_UPLOADS`` allows, as a new study.
"""

from __future__ import annotations

import builtins
import contextlib
import io
import json
import logging
import os
import shutil
import threading
import zipfile
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

from sqlalchemy import func, select, update

from miss import __version__
from miss.errors import BadParameter, MissError, WrongStudy
from miss.pacs import client
from miss.pacs.server import PacsServer
from miss.pacs.stl import Origin, encapsulate
from miss.server import audit
from miss.server.accounts import User
from miss.server.core.errors import NotFound, NotReady, TooManyRequests
from miss.server.core.settings import Settings
from miss.server.storage import formats
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
from miss.server.volumes.ingest import Reading, ingest
from miss.server.volumes.uploads import Upload

log = logging.getLogger("miss.server")

#: Most instances one imported series may have (slices; a multi-frame file counts once).
MAX_INSTANCES = 5000
#: Largest DICOM SEG or RT-STRUCT series retrieved (an uncompressed SEG of a 20-slice CT
#: with 31 segments is 17 MB).
MAX_SEGMENTATION_BYTES = 1 << 30
#: The nice increment of an import whose account has more waiting: its confined reader
#: and its thread (weight 15 against the server's 1024 on a contended core, below another
#: account's job at nice 15, weight 36: a flood of imports had taken three times a job's
#: share at nice 10).
READ_NICE = 19
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


def _behind() -> None:
    """A ``behind`` pool thread's start: its own nice value to ``READ_NICE`` (where the
    system allows it; a thread that cannot runs at the server's)."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), READ_NICE)


#: One waiting import: its id, its owner, its PACS.
Waiting = tuple[str, User, PacsServer]


class PacsImports:
    """Imports run on ``settings.pacs_imports`` threads; each is a row in ``pacs_imports``
    that its owner polls (``GET /api/pacs/imports/{id}``).

    An account may have ``settings.pacs_imports_per_user`` queued or running (429 past
    that), and a free thread takes the next import of the account served longest ago,
    not the oldest import: one account's queue never holds up another's import. One
    account runs at most all threads but one at once (at least one), so a thread is free
    for the next account's import even while the first keeps posting; and an import
    whose account has more imports waiting runs behind the server (``READ_NICE``: its
    confined reads, and its retrieval, checks and writes on a thread of the ``behind``
    pool), so a burst of imports leaves the cores to others' requests and jobs."""

    def __init__(self, store: Store, settings: Settings, reading: Callable[[], Reading]) -> None:
        self.store, self.settings, self.reading = store, settings, reading
        self.pool = ThreadPoolExecutor(settings.pacs_imports, thread_name_prefix="miss-pacs")
        # Linux: a thread's nice value is its own; raised once, never lowered (RLIMIT_NICE).
        self.behind = ThreadPoolExecutor(
            settings.pacs_imports, thread_name_prefix="miss-pacs-behind", initializer=_behind
        )
        self._lock = threading.Lock()
        self._waiting: dict[str, deque[Waiting]] = {}  # owner id -> its imports, in order
        self._served: dict[str, int] = {}  # owner id -> when its last import started (turn)
        self._running: dict[str, int] = {}  # owner id -> its imports running now
        self._per_account = max(1, settings.pacs_imports - 1)
        self._turns = 0

    def stop(self) -> None:
        """Stop taking imports; queued ones are cancelled, running ones are not waited for."""
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.behind.shutdown(wait=False, cancel_futures=True)

    def submit(
        self, user: User, server: PacsServer, study: str, series: str, segmentation: str
    ) -> PacsImportRow:
        """Queue an import of ``series`` (and of ``segmentation``, if given) from ``server``
        for ``user``; the new row. TooManyRequests (429) when the account has
        ``MISS_PACS_IMPORTS_PER_USER`` imports queued or running already."""
        row = PacsImportRow(
            id=new_id(), owner_id=user.id, pacs=server.name, study=study, series=series,
            segmentation=segmentation,
        )  # fmt: skip
        with self._lock:  # counted and added at once: two posts cannot both take the last place
            self._check_room(user)
            with self.store.session.begin() as s:
                s.add(row)
            self._waiting.setdefault(user.id, deque()).append((row.id, user, server))
        self.pool.submit(self._next)
        return row

    def _check_room(self, user: User) -> None:
        limit = self.settings.pacs_imports_per_user
        with self.store.session() as s:
            query = select(func.count()).where(
                PacsImportRow.owner_id == user.id, PacsImportRow.status.in_((QUEUED, RUNNING))
            )
            count = s.scalar(query) or 0
        if count >= limit:
            raise TooManyRequests(
                f"you have {count} PACS imports queued or running, the most one account may "
                f"have (MISS_PACS_IMPORTS_PER_USER={limit}); wait until one is done or failed "
                "(GET /api/pacs/imports) and import again."
            )

    def _next(self) -> None:
        """Run the first waiting import of the account whose last one started longest ago
        (accounts not served yet first) among those below their share of the threads;
        each pool task runs at most one import, and an import that ends asks for the
        next (one held back by the share waits for that)."""
        with self._lock:
            owners = [
                o
                for o, q in self._waiting.items()
                if q and self._running.get(o, 0) < self._per_account
            ]
            if not owners:
                return
            owner = min(owners, key=lambda o: self._served.get(o, 0))
            self._turns += 1
            self._served[owner] = self._turns
            self._running[owner] = self._running.get(owner, 0) + 1
            import_id, user, server = self._waiting[owner].popleft()
            if not self._waiting[owner]:
                del self._waiting[owner]
            busy = owner in self._waiting or self._running[owner] > 1
        try:
            if busy:  # this account has more imports waiting: the whole import goes behind
                self.behind.submit(self._run, import_id, user, server, busy).result()
            else:
                self._run(import_id, user, server, busy)
        finally:
            with self._lock:
                self._running[owner] -= 1
                if not self._running[owner]:
                    del self._running[owner]
                more = bool(self._waiting)
            if more:
                self.pool.submit(self._next)

    def get(self, import_id: str, user: User) -> PacsImportRow:
        """The import if it is ``user``'s; NotFound (404) otherwise."""
        with self.store.session() as s:
            row = s.get(PacsImportRow, import_id)
        if row is None or row.owner_id != user.id:
            raise NotFound(f"no import {import_id!r}; GET /api/pacs/imports lists yours.")
        return row

    def list(self, user: User, limit: int = 50) -> list[PacsImportRow]:
        """``user``'s latest ``limit`` imports, newest first."""
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

    def _run(self, import_id: str, user: User, server: PacsServer, busy: bool) -> None:
        row = self.get(import_id, user)
        reading = self.reading()
        if busy:  # this account has more imports waiting: its reading goes behind others
            reading = (reading[0], replace(reading[1], nice=READ_NICE))
        self._set(import_id, status=RUNNING, stage="listing the series", progress=0.02)
        work: Path | None = None
        try:
            self.store.check_free_space(self.settings.min_free_bytes)
            work = self.store.tmp_dir()
            volume, labels = self._import(row, user, server, work, reading)
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
        self, row: PacsImportRow, user: User, server: PacsServer, work: Path, reading: Reading
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
        held = client.study_attributes(server, row.study) or {}
        origin = {  # as the PACS has them: a model is sent back only where they still hold
            "pacs": server.name,
            "study": row.study,
            "series": row.series,
            "patient_id": held.get("PatientID", ""),
            "issuer": held.get("IssuerOfPatientID", ""),
            "instances": [list(i) for i in instances],
        }
        volume = ingest(self.store, upload, work, reading, user.id, origin)
        labels = 0
        if row.segmentation != "none":
            self._set(row.id, stage="looking for segmentations", progress=0.9)
            try:
                labels = self._segmentation(row, server, volume, work, listed, reading)
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
        listed: builtins.list[dict[str, Any]],  # builtins': this class has a list()
        reading: Reading,
    ) -> int:
        """Lay the study's SEG or RT-STRUCT of this series over the volume; its label
        count (0: none found)."""
        from miss.server.volumes import labelmaps

        found = find_segmentation(server, row.study, row.series, row.segmentation, work, listed)
        if found is None:
            return 0
        scan = self.store.open_volume(volume.id)
        labels, meta = labelmaps.read_segmentation(found, scan, work, reading)
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


#: Why a volume that was uploaded (not imported from the PACS) gets no model sent.
UPLOADED = (
    "this volume was uploaded, not imported from the PACS: MISS files a model only in the "
    "study its volume was imported from, checked on the PACS first; nothing was sent. "
    "Import the series from the PACS and send a model of it (an administrator may allow "
    "uploads to go as a new study: MISS_PACS_SEND_UPLOADS=1)."
)


def destination(store: Store, settings: Settings, server: PacsServer, volume: VolumeRow) -> Origin:
    """Where a model of ``volume`` goes on ``server``: the study it was imported from,
    after the PACS confirmed (QIDO-RS) that the study still has its patient and source
    series; or, for an uploaded volume and only with ``settings.pacs_send_uploads``, a
    new study of its own. :class:`WrongStudy` (409) for anything else."""
    record = store.get_identity(volume.id)
    data = record.data if record else {}
    came = data.get("origin") or {}
    if came:
        return _back_home(server, volume, data, came)
    if not settings.pacs_send_uploads:
        raise WrongStudy(UPLOADED)
    return new_study(data.get("patient") or {})


def _back_home(
    server: PacsServer, volume: VolumeRow, data: dict[str, Any], came: dict[str, Any]
) -> Origin:
    """The study a PACS import came from, checked on that PACS."""
    study, series = str(came.get("study", "")), str(came.get("series", ""))
    if came.get("pacs") != server.name:
        raise WrongStudy(
            f"this volume was imported from PACS {came.get('pacs')!r}; a model goes back only "
            f"into the study it came from there, not to {server.name!r}; nothing was sent. "
            "Leave 'pacs' out to send it where it came from.",
            study,
        )
    patient = {k: str(v) for k, v in (data.get("patient") or {}).items()}
    # imports before the PACS's own patient ID was recorded: the retrieved files' (they
    # were checked to be of this study and series as they came)
    patient_id = str(came.get("patient_id") or patient.get("PatientID", ""))
    held = client.check_study(server, study, series, patient_id, str(came.get("issuer", "")))
    back = {new: old for old, new in (data.get("uids") or {}).items()}
    return Origin(
        study=study,
        series=series,
        frame_of_reference=back.get(volume.info.get("frame_of_reference") or "", ""),
        patient=patient | {k: v for k, v in held.items() if v},
        sources=[tuple(i) for i in came.get("instances") or []],
    )


def new_study(patient: dict[str, Any]) -> Origin:
    """A new study (fresh study, series and frame UIDs; never the uploaded file's) for
    a model of an uploaded volume whose file named ``patient``."""
    from datetime import datetime

    from pydicom.uid import generate_uid

    if not str(patient.get("PatientID", "")).strip():
        raise WrongStudy(
            "this volume's file names no patient ID, so a model of it has no patient to be "
            "filed under on the PACS; nothing was sent. Import the series from the PACS."
        )
    keep = ("PatientName", "PatientID", "IssuerOfPatientID", "PatientBirthDate", "PatientSex")
    now = datetime.now()
    attributes = {k: str(patient[k]) for k in keep if patient.get(k)} | {
        "StudyDate": now.strftime("%Y%m%d"),
        "StudyTime": now.strftime("%H%M%S"),
        "StudyDescription": "MISS model of an uploaded volume",
    }
    return Origin(generate_uid(), "", generate_uid(), attributes)


def stl_parts(folder: Path, data: bytes | None = None) -> list[tuple[str, bytes]]:
    """(part name, STL bytes) a part of a finished model: from its stored scene (the
    download's ``model.stl`` is one solid of every part); a model from before that has
    ``model.stl`` (or ``data``, its bytes): one STL, or a zip with one STL a part and
    ``scene.json``."""
    if data is None and (folder / formats.MESH_FILE).is_file():
        from miss.export import export

        stored = formats.read_scene(folder / formats.MESH_FILE)
        parts = stored.scene.parts
        if len(parts) == 1:  # the download's bytes, byte for byte
            whole = export(stored.scene, "stl", title=stored.title, metadata=stored.metadata)
            return [(parts[0].name, whole)]
        return [(part.name, export(part.mesh, "stl", title=part.name)) for part in parts]
    data = (folder / "model.stl").read_bytes() if data is None else data
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
    store: Store,
    settings: Settings,
    server: PacsServer,
    model: ModelRow,
    volume: VolumeRow,
    user: User,
) -> dict[str, Any]:
    """Send a finished model as one Encapsulated STL instance a part, in a new series of
    the study :func:`destination` gives; what was stored."""
    if volume.owner_id != user.id:
        raise NotFound(f"no model {model.id!r} of yours; only a volume's owner sends its models.")
    if model.status != DONE:
        raise NotReady(f"model {model.id!r} is {model.status}; send it once it is done.")
    origin = destination(store, settings, server, volume)
    parts = stl_parts(store.model_dir(model.id))  # one instance a part
    description = describe(model, volume)
    titles = [p.get("name", "") for p in (model.stats or {}).get("parts") or []]
    named = [(title or name or description, stl) for (name, stl), title in _pad(parts, titles)]
    datasets = encapsulate(named, origin, description, f"MISS {__version__}")
    stored = client.store(server, datasets, origin.study)
    return {
        "pacs": server.name,
        "study_uid": origin.study,
        "series_uid": str(datasets[0].SeriesInstanceUID),
        "sop_instance_uids": stored,
        "description": description,
        "parts": [title for title, _ in named],
    }


def _pad(parts: list[tuple[str, bytes]], titles: list[str]) -> list[tuple[tuple[str, bytes], str]]:
    return [(part, titles[i] if i < len(titles) else "") for i, part in enumerate(parts)]
