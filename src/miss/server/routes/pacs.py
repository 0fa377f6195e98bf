"""``/api/pacs``: search the hospital's PACS, import a series as a volume, and
``POST /api/models/{id}/pacs``: send a model back into the patient's study.

Only accounts with the ``pacs`` permission see any of it: for everyone else (and on a
server with no PACS configured) every route here answers 404. Every query, import and
send (and refused send, with the study it was for) is in the audit log (filter names and
counts, never the patient's name or ID).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal, cast

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from miss.errors import MissError
from miss.pacs import client
from miss.pacs.server import PacsServer
from miss.server import audit, quota
from miss.server.accounts import User
from miss.server.core.deps import ModelDep, PacsImportsDep, SettingsDep, StoreDep, UserDep
from miss.server.core.errors import NotFound
from miss.server.core.settings import Settings
from miss.server.pacs_exchange import send_model
from miss.server.storage.db import PacsImportRow

router = APIRouter(tags=["pacs"])
NO_PACS = (
    "not found: this account has no PACS access (an administrator grants it) or this server "
    "has no PACS configured (MISS_PACS_URL)."
)


async def pacs_user(user: UserDep, settings: SettingsDep) -> User:
    """The user, if it may use the PACS and there is one; 404 otherwise."""
    if not user.pacs or not settings.pacs:
        raise NotFound(NO_PACS)
    return user


PacsUserDep = Annotated[User, Depends(pacs_user)]
PacsName = Annotated[
    str | None, Query(max_length=64, description="which PACS (default: the first)")
]


def _server(settings: Settings, name: str | None) -> PacsServer:
    server = settings.pacs_server(name)
    if server is None:
        names = ", ".join(p.name for p in settings.pacs)
        raise NotFound(f"no PACS named {name!r}; this server knows {names}.")
    return server


class PacsOut(BaseModel):
    """A PACS this server may search and import from."""

    name: str


class StudyOut(BaseModel):
    """A study found on the PACS: patient, date, description, modalities and counts."""

    study: str
    patient_id: str
    patient_name: str
    birth_date: str
    sex: str
    study_date: str
    accession: str
    description: str
    modalities: list[str]
    series_count: int | None
    instances: int | None


class StudiesOut(BaseModel):
    """A page of studies found on the PACS; ``more`` when there are further pages."""

    pacs: str
    studies: list[StudyOut]
    offset: int
    limit: int
    more: bool


class SeriesOut(BaseModel):
    """A series of a study on the PACS, and whether (or why not) it can be imported."""

    series: str
    modality: str
    description: str
    number: int | None
    instances: int | None
    importable: bool
    segmentation: bool
    reason: str | None


class ImportRequest(BaseModel):
    """An import of one image series from the PACS, with the segmentation to lay over it
    (found, named, or none)."""

    model_config = ConfigDict(extra="forbid")

    study: str = Field(max_length=64, description="Study Instance UID (from the search)")
    series: str = Field(max_length=64, description="Series Instance UID of an image series")
    segmentation: str = Field(
        default="auto",
        max_length=64,
        description="'auto': the study's newest SEG or RT-STRUCT that refers to the series "
        "becomes the volume's label map; 'none'; or that series' UID",
    )
    pacs: str | None = Field(default=None, max_length=64, description="default: the first PACS")


ImportStatus = Literal["queued", "running", "done", "failed"]


class ImportOut(BaseModel):
    """An import from the PACS: its state, and the volume it made once done."""

    id: str
    pacs: str
    status: ImportStatus
    stage: str
    progress: float
    name: str
    volume_id: str | None
    labels: int
    error: str | None
    created_at: datetime
    finished_at: datetime | None


class SendRequest(BaseModel):
    """Where to send a model (as DICOM Encapsulated STL, one instance a part)."""

    model_config = ConfigDict(extra="forbid")

    pacs: str | None = Field(
        default=None, max_length=64, description="default: the PACS the volume came from"
    )


class SendOut(BaseModel):
    """What was stored on the PACS: the new series' UIDs and its parts."""

    pacs: str
    study_uid: str
    series_uid: str
    sop_instance_uids: list[str]
    description: str
    parts: list[str]


def import_out(row: PacsImportRow) -> ImportOut:
    """The API's view of an import row."""
    return ImportOut(
        id=row.id, pacs=row.pacs, status=cast(ImportStatus, row.status), stage=row.stage, progress=row.progress,
        name=row.name, volume_id=row.volume_id, labels=row.labels, error=row.error,
        created_at=row.created_at, finished_at=row.finished_at,
    )  # fmt: skip


@router.get("/api/pacs", response_model=list[PacsOut])
def list_pacs(settings: SettingsDep, user: PacsUserDep) -> list[PacsOut]:
    """The PACS this server knows (the first is the default)."""
    return [PacsOut(name=p.name) for p in settings.pacs]


@router.get("/api/pacs/studies", response_model=StudiesOut)
def search_studies(
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    user: PacsUserDep,
    pacs: PacsName = None,
    patient_id: Annotated[str | None, Query(max_length=64)] = None,
    patient_name: Annotated[str | None, Query(max_length=64)] = None,
    accession: Annotated[str | None, Query(max_length=64)] = None,
    study_date: Annotated[
        str | None, Query(max_length=64, description="YYYYMMDD or a range")
    ] = None,
    modality: Annotated[str | None, Query(max_length=16)] = None,
    offset: Annotated[int, Query(ge=0, le=100_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=client.MAX_PAGE)] = 25,
) -> StudiesOut:
    """Studies on the PACS (QIDO-RS), ``limit`` a page; ``more`` says whether another
    page follows. A name without ``*`` matches as a prefix."""
    server = _server(settings, pacs)
    given = {
        "patient_id": patient_id, "patient_name": patient_name, "accession": accession,
        "study_date": study_date, "modality": modality,
    }  # fmt: skip
    filters = client.search_filters(given)
    page = client.search_studies(server, filters, offset, limit)
    audit.record(
        store, "pacs_search", user.name, server.name, audit.address(request),
        filters=sorted(k for k, v in given.items() if v), results=len(page.rows),
    )  # fmt: skip
    studies = [StudyOut(**row) for row in page.rows]
    return StudiesOut(
        pacs=server.name, studies=studies, offset=page.offset, limit=page.limit, more=page.more
    )


@router.get("/api/pacs/studies/{study}/series", response_model=list[SeriesOut])
def list_series(
    study: str, settings: SettingsDep, user: PacsUserDep, pacs: PacsName = None
) -> list[SeriesOut]:
    """The study's series with modality, description, instance count, and whether MISS
    can model them (``importable``; SEG and RT-STRUCT series come with their images)."""
    return [SeriesOut(**row) for row in client.search_series(_server(settings, pacs), study)]


@router.post(
    "/api/pacs/import",
    status_code=202,
    response_model=ImportOut,
    responses={404: {"description": "no PACS access"}},
)
def start_import(
    body: ImportRequest,
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    user: PacsUserDep,
    imports: PacsImportsDep,
) -> JSONResponse:
    """Bring a series in as a volume (de-identified at the door, as an upload is). Answers
    at once with the import; poll ``GET /api/pacs/imports/{id}`` until ``done`` (it then
    names the volume) or ``failed`` (with the reason; post again to retry)."""
    server = _server(settings, body.pacs)
    client.check_uid(body.study, "study")
    client.check_uid(body.series, "series")
    if body.segmentation not in ("auto", "none"):
        client.check_uid(body.segmentation, "segmentation")
    store.check_free_space(settings.min_free_bytes)
    quota.check(store, user, settings.quota_bytes)  # 507 once the account's quota is full
    row = imports.submit(user, server, body.study, body.series, body.segmentation)
    audit.record(
        store, "pacs_import_start", user.name, row.id, audit.address(request), pacs=server.name
    )
    out = import_out(row).model_dump(mode="json")
    return JSONResponse(out, status_code=202, headers={"Location": f"/api/pacs/imports/{row.id}"})


@router.get("/api/pacs/imports", response_model=list[ImportOut])
def list_imports(user: PacsUserDep, imports: PacsImportsDep) -> list[ImportOut]:
    """Your imports, newest first."""
    return [import_out(row) for row in imports.list(user)]


@router.get("/api/pacs/imports/{import_id}", response_model=ImportOut)
def get_import(import_id: str, user: PacsUserDep, imports: PacsImportsDep) -> ImportOut:
    """The state of one of your PACS imports, and its volume once done. 404 when it is not
    yours, or this account has no PACS access."""
    return import_out(imports.get(import_id, user))


@router.post(
    "/api/models/{model_id}/pacs",
    response_model=SendOut,
    responses={
        404: {"description": "no PACS access, or not your model"},
        409: {
            "description": "the model is not done yet, or would be filed where it does not "
            "belong (not imported from this PACS; the study's patient or series changed)"
        },
        502: {"description": "the PACS refused it or did not answer"},
    },
)
def send_to_pacs(
    model: ModelDep,
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    user: PacsUserDep,
    body: SendRequest | None = None,
) -> Any:
    """Send the model into the patient's original study on the PACS: one DICOM
    Encapsulated STL instance a part (patient LPS mm, the source series' frame of
    reference), in a new series described as what it is. Only the volume's owner, only
    for a volume imported from that PACS whose study the PACS confirms still has the
    patient and series (409 otherwise; an uploaded volume's model goes as a new study
    where ``MISS_PACS_SEND_UPLOADS`` allows). Every send and refusal is audited with the
    study it went (or would have gone) to."""
    volume = store.get_volume(model.volume_id)
    record = store.get_identity(volume.id)
    came_from = ((record.data if record else {}).get("origin") or {}).get("pacs")
    name = (body.pacs if body else None) or (came_from if settings.pacs_server(came_from) else None)
    server = _server(settings, name)
    where = audit.address(request)
    try:
        sent = send_model(store, settings, server, model, volume, user)
    except MissError as exc:
        audit.record(
            store, "pacs_send_refused", user.name, model.id, where, pacs=server.name,
            study=getattr(exc, "study", ""), reason=str(exc)[:300],
        )  # fmt: skip
        raise
    audit.record(
        store, "pacs_send", user.name, model.id, where, pacs=server.name,
        study=sent["study_uid"], series=sent["series_uid"], instances=sent["sop_instance_uids"],
    )  # fmt: skip
    return sent
