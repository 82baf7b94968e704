"""GET /compensation: the thermal growth at the tool for a compensation controller (docs/api.md,
docs/design/growth.md): axial and radial growth in µm and 0.1-µm integers, 95 % CIs, the forecast, the
controller values, the sensor sensitivity, with the policy's verdict on the growth
(``service.serve.policy``). GET /compensation/section: the section's outline and its displacement (µm) by
the live field, for the dashboard's exaggerated drawing. GET /compensation/reference: the compensation zero
in use; POST (token): set it now. GET /compensation/mechanics: the commissioned mechanics in use; POST
(token): commission them from a measured thermal test (the files' contents; the fit runs in this request's
thread, seconds to a minute: the service's own core over the test's logs). GET /compensation/measurements:
the probe readings taken; POST (token): one more, absorbed into the mechanical posterior unless it disagrees
beyond its CI (docs/commissioning.md, "Probe measurements").

A plain (not async) endpoint: FastAPI runs it in a worker thread, because the service may build the growth
model once and its per-condition terms (~0.3 s) on a new identification or condition; never on the loop.
"""

from __future__ import annotations

import base64
import binascii
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Body, Request

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep, WriteAccess
from api.errors import ApiError
from api.schemas import (
    CompensationOut,
    CompensationSectionOut,
    MeasurementIn,
    MeasurementOut,
    MeasurementPostOut,
    MechanicsCommissionIn,
    MechanicsCommissionOut,
    MechanicsOut,
    ReferenceIn,
    ReferenceOut,
    compensation_out,
    compensation_section_out,
    measurement_out,
    measurement_post_out,
    mechanics_out,
    reference_out,
)
from service.contracts.errors import CommissioningError, NotReadyError
from service.contracts.mechanics import EXAMPLE_NOTE, is_shipped_example
from service.contracts.probe import ProbeError

router = APIRouter(tags=["compensation"], dependencies=[ReadAccess])


def _no_growth() -> ApiError:
    return ApiError(
        status=503,
        code="no_data",
        message="no identification or no live field yet",
        headers={"Retry-After": "5"},
    )


@router.get(
    "/compensation",
    response_model=CompensationOut,
    responses={503: {"description": "no identification or no live field yet"}},
    summary="thermal growth at the tool (µm, 0.1 µm), 95 % CI, forecast, controller values, status",
)
def get_compensation(service: ServiceDep, clock: ClockDep, spindle_id: SpindleIdDep) -> CompensationOut:
    snap = service.compensation()
    if snap is None:
        raise _no_growth()
    return compensation_out(snap, clock(), spindle_id=spindle_id)


@router.get(
    "/compensation/section",
    response_model=CompensationSectionOut,
    responses={503: {"description": "no identification or no live field yet"}},
    summary="the spindle's section outline and its displacement (u_r, u_z, µm) by the live field",
)
def get_compensation_section(
    service: ServiceDep, clock: ClockDep, spindle_id: SpindleIdDep
) -> CompensationSectionOut:
    snap = service.compensation_section()
    if snap is None:
        raise _no_growth()
    return compensation_section_out(snap, clock(), spindle_id=spindle_id)


@router.get(
    "/compensation/reference",
    response_model=ReferenceOut,
    responses={404: {"description": "no compensation zero set"}},
    summary="the compensation zero in use: uniform temperature of growth 0, when, how and by whom",
)
def get_reference(service: ServiceDep) -> ReferenceOut:
    ref = service.compensation_reference()
    if ref is None:
        raise ApiError(
            status=404,
            code="not_found",
            message="no compensation zero set: POST /api/v1/compensation/reference (or chtc commission zero)",
        )
    return reference_out(ref)


@router.post(
    "/compensation/reference",
    response_model=ReferenceOut,
    responses={
        401: {"description": "no token"},
        403: {"description": "wrong token"},
        409: {"description": "no live state converged yet (give temperature_c, or wait)"},
    },
    summary="set the compensation zero now (needs the bearer token); stored, restored at every start",
)
def post_reference(
    service: ServiceDep, _: WriteAccess, body: Annotated[ReferenceIn | None, Body()] = None
) -> ReferenceOut:
    req = body if body is not None else ReferenceIn.model_validate({})
    try:
        ref = service.set_compensation_reference(
            temperature_c=req.temperature_c, source=req.source, set_by=req.set_by or req.source
        )
    except NotReadyError as err:
        raise ApiError(status=409, code="conflict", message=str(err)) from err
    return reference_out(ref)


@router.get(
    "/compensation/mechanics",
    response_model=MechanicsOut,
    responses={404: {"description": "not commissioned: the spindle description's mechanics, uncalibrated"}},
    summary="the commissioned mechanics in use: mount restraint and α factors with their posterior",
)
def get_mechanics(service: ServiceDep) -> MechanicsOut:
    cal = service.compensation_mechanics()
    if cal is None:
        raise ApiError(
            status=404,
            code="not_found",
            message="the mechanics are not commissioned: POST /api/v1/compensation/mechanics "
            "(or chtc commission growth)",
        )
    return mechanics_out(cal)


@router.post(
    "/compensation/mechanics",
    response_model=MechanicsCommissionOut,
    responses={
        401: {"description": "no token"},
        403: {"description": "wrong token"},
        409: {
            "description": "the model does not explain the test (nothing stored; see the message, or force)"
        },
        422: {
            "description": "a file that cannot be read, or `can_log_base64` that is not base64 (the message "
            "names the file, line and field)"
        },
    },
    summary="commission the growth's mechanics from a measured thermal test (needs the bearer token); "
    "stored, restored at every start",
)
def post_mechanics(
    service: ServiceDep, _: WriteAccess, body: Annotated[MechanicsCommissionIn, Body()], request: Request
) -> MechanicsCommissionOut:
    from drivers.logs import LogFormatError

    simulated = bool(getattr(getattr(request.app.state, "clock_info", None), "simulated", False))
    if is_shipped_example(body.displacements_csv) and not simulated and not body.force:
        raise ApiError(
            status=409, code="conflict", message=f"nothing stored: {EXAMPLE_NOTE} (force to store it anyway)"
        )

    try:
        can_bytes = base64.b64decode(body.can_log_base64, validate=True)
    except (binascii.Error, ValueError) as err:
        raise ApiError(status=422, code="invalid", message=f"can_log_base64: not base64 ({err})") from err
    with tempfile.TemporaryDirectory(prefix="chtc-commission-") as tmp:
        d = Path(tmp)
        temps, canlog, disp = (
            d / "temperatures.csv",
            d / f"can.{body.can_log_format}",
            d / "displacements.csv",
        )
        temps.write_text(body.temperatures_csv, encoding="utf-8")
        canlog.write_bytes(can_bytes)
        disp.write_text(body.displacements_csv, encoding="utf-8")
        try:
            rep, stored = service.commission_mechanics(
                temperatures=temps,
                canlog=canlog,
                displacements=disp,
                set_by=body.set_by or body.source,
                source=body.source,
                force=body.force,
            )
        except (CommissioningError, LogFormatError) as err:
            message = str(err).replace(str(d) + "/", "")
            raise ApiError(status=422, code="invalid", message=message) from err
    report = rep.as_dict()
    if not stored:
        raise ApiError(
            status=409,
            code="conflict",
            message=f"nothing stored: {report['verdict']} (force to store it anyway)",
        )
    return MechanicsCommissionOut(stored=stored, mechanics=mechanics_out(rep.calibration), report=report)


@router.get(
    "/compensation/measurements",
    response_model=list[MeasurementOut],
    summary="the probe readings taken (restored and new, absorbed or flagged), newest first",
)
def get_measurements(service: ServiceDep) -> list[MeasurementOut]:
    return [measurement_out(m) for m in service.compensation_measurements()]


@router.post(
    "/compensation/measurements",
    response_model=MeasurementPostOut,
    responses={
        401: {"description": "no token"},
        403: {"description": "wrong token"},
        422: {
            "description": "a bad field, `at` in the future or older than the live state's kept history, or "
            "no compensation zero to measure against (the message names it)"
        },
        503: {"description": "the growth model is not available"},
    },
    summary="a probe reading of the axial growth (needs the bearer token): absorbed into the mechanical "
    "posterior (the served CI tightens) unless it disagrees beyond its CI (flagged); stored, replayed at "
    "start",
)
def post_measurement(
    service: ServiceDep, _: WriteAccess, body: Annotated[MeasurementIn, Body()]
) -> MeasurementPostOut:
    try:
        m = service.add_measurement(
            at=body.at, axial_um=body.axial_um, sd_um=body.sd_um, set_by=body.set_by or "api", source="api"
        )
    except ProbeError as err:
        field = str(err).split(":", 1)[0]
        raise ApiError(status=422, code="invalid", message=str(err), field=field) from err
    return measurement_post_out(m, service.compensation_mechanics())
