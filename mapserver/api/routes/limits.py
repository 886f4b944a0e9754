"""``GET /v1/limits``: the limits the server refuses input by, and the fixed bounds of odometry and other values."""

from __future__ import annotations

from fastapi import APIRouter

from mapserver import bounds
from mapserver.api.deps import ReadAccess, ServicesDep
from mapserver.api.schemas import ErrorPublic, LimitsPublic, OdometryRulesPublic, ValueBoundsPublic

router = APIRouter(prefix="/v1/limits", tags=["limits"])


@router.get("", operation_id="get_limits", response_model=LimitsPublic,
            responses={401: {"model": ErrorPublic}, 403: {"model": ErrorPublic}})  # fmt: skip
def read_limits(services: ServicesDep, _token: ReadAccess) -> LimitsPublic:
    """Return every limit by name: a refusal by one (413) names it in ``detail`` and ``limit``."""
    rules = OdometryRulesPublic(
        max_position_m=bounds.MAX_POSITION_M, max_speed_m_s=bounds.MAX_SPEED_M_S,
        max_yaw_rate_rad_s=bounds.MAX_YAW_RATE_RAD_S, max_bad_fraction=bounds.MAX_BAD_FRACTION,
    )  # fmt: skip
    values = ValueBoundsPublic(
        max_position_m=bounds.MAX_POSITION_M, max_angle_rad=bounds.MAX_ANGLE_RAD, max_time_s=bounds.MAX_TIME_S,
        max_query_coordinate_m=bounds.MAX_QUERY_COORDINATE_M,
    )  # fmt: skip
    return LimitsPublic(**services.settings.limits(), odometry=rules, values=values)
