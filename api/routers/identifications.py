"""Identifications: list (paginated, since/until), one by id, start one now (bearer token), job state."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Path, Query, Request
from fastapi.responses import JSONResponse

from api.deps import ReadAccess, ServiceDep, SpindleIdDep, UtcDateTime, WriteAccess
from api.errors import invalid
from api.schemas import (
    IdentificationOut,
    IdentificationPageOut,
    IdentificationRequest,
    JobOut,
    identification_out,
    job_out,
)

router = APIRouter(tags=["identifications"])
PREFIX = "/api/v1"
MAX_ID = 2**63 - 1  # the database's BIGINT; larger ids cannot exist (and would overflow the driver)


@router.get(
    "/identifications",
    response_model=IdentificationPageOut,
    dependencies=[ReadAccess],
    summary="stored identifications, newest first",
    responses={
        422: {"description": "a bad parameter, or `until` not later than `since` (the message names it)"}
    },
)
def list_identifications(
    service: ServiceDep,
    spindle_id: SpindleIdDep,
    since: Annotated[
        UtcDateTime | None, Query(description="finished at or after (ISO-8601 with offset)")
    ] = None,
    until: Annotated[
        UtcDateTime | None,
        Query(description="finished before (ISO-8601 with offset); later than since (else 422)"),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=100)] = 20,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
) -> IdentificationPageOut:
    if since is not None and until is not None and until <= since:
        raise invalid("until", "must be later than since")
    page = service.list_identifications(since=since, until=until, limit=limit, offset=offset)
    nxt = offset + len(page.items)
    return IdentificationPageOut(
        spindle_id=spindle_id,
        items=[identification_out(r) for r in page.items],
        total=page.total,
        limit=limit,
        offset=offset,
        next_offset=nxt if nxt < page.total else None,
        partial=page.partial_reason is not None,
        partial_reason=page.partial_reason,
    )


@router.get(
    "/identifications/jobs/{job_id}",
    response_model=JobOut,
    dependencies=[ReadAccess],
    summary="state of a requested identification",
)
def get_job(
    service: ServiceDep, spindle_id: SpindleIdDep, job_id: Annotated[str, Path(max_length=64)]
) -> JobOut:
    return job_out(service.job(job_id), PREFIX, spindle_id=spindle_id)


@router.get(
    "/identifications/{identification_id}",
    response_model=IdentificationOut,
    dependencies=[ReadAccess],
    summary="one stored identification",
)
def get_identification(
    service: ServiceDep, identification_id: Annotated[int, Path(ge=1, le=MAX_ID)]
) -> IdentificationOut:
    return identification_out(service.get_identification(identification_id))


@router.post(
    "/identifications",
    response_model=JobOut,
    status_code=202,
    summary="start an identification now (needs the bearer token)",
    responses={
        401: {"description": "no token"},
        403: {"description": "wrong token"},
        409: {"description": "busy"},
    },
)
def start_identification(
    request: Request,
    service: ServiceDep,
    spindle_id: SpindleIdDep,
    _: WriteAccess,
    body: Annotated[IdentificationRequest | None, Body()] = None,
) -> JSONResponse:
    reason = body.reason if body is not None else "manual"
    job = job_out(service.request_identification(reason), PREFIX, spindle_id=spindle_id)
    return JSONResponse(job.model_dump(mode="json"), status_code=202, headers={"Location": job.href})
