"""``GET /healthz``: liveness (no token needed)."""

from __future__ import annotations

from fastapi import APIRouter

from mapserver.api.schemas import HealthPublic

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="get_health", response_model=HealthPublic)
def get_health() -> HealthPublic:
    """Return ``{"status": "ok"}`` while the server runs."""
    return HealthPublic()
