"""``GET /v1/limits``: the limits the server refuses input by, and the fixed bounds odometry must keep."""

from __future__ import annotations

from fastapi import APIRouter

from mapserver.api.deps import ReadAccess, ServicesDep
from mapserver.api.schemas import ErrorPublic, LimitsPublic, OdometryRulesPublic
from mapserver.ingest import odometry

router = APIRouter(prefix="/v1/limits", tags=["limits"])


@router.get("", operation_id="get_limits", response_model=LimitsPublic,
            responses={401: {"model": ErrorPublic}, 403: {"model": ErrorPublic}})  # fmt: skip
def read_limits(services: ServicesDep, _token: ReadAccess) -> LimitsPublic:
    """Return every limit by name: a refusal by one (413) names it in ``detail`` and ``limit``."""
    rules = OdometryRulesPublic(
        max_position_m=odometry.MAX_POSITION_M, max_speed_m_s=odometry.MAX_SPEED_M_S,
        max_yaw_rate_rad_s=odometry.MAX_YAW_RATE_RAD_S, max_bad_fraction=odometry.MAX_BAD_FRACTION,
    )  # fmt: skip
    return LimitsPublic(**services.settings.limits(), odometry=rules)
