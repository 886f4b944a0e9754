"""``/v1/maps/{name}/links``: manual links — add one (write token), list a map's (read).

``POST`` joins two experiences as the same place or with a stated transform (:mod:`mapserver.atlas.manual_links`):
within the map, or to an experience of another map, which then merges into it. The answer says whether the
robust check kept the link on or flagged it (switched off: it contradicts the map). The link is a merge event:
``POST /v1/merges/{id}/undo`` removes it.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from mapserver.api.deps import ReadAccess, ServicesDep, WriteAccess
from mapserver.api.routes.maps import MAP_ERRORS, MAX_ID, MapName
from mapserver.api.schemas import ErrorPublic
from mapserver.api.services import Services
from mapserver.atlas.manual_links import LinkRequest, link_experiences
from mapserver.store import get_map
from mapserver.store.manual_links import manual_links
from mapserver.store.tokens import TokenRecord

router = APIRouter(prefix="/v1/maps", tags=["links"])
WRITE_ERRORS: dict[int | str, dict[str, Any]] = {**MAP_ERRORS, 400: {"model": ErrorPublic}, 409: {"model": ErrorPublic}}


class TransformIn(BaseModel):
    """The pose of ``to`` in ``from``'s frame (metres, radians); every field 0 by default: the same place."""

    model_config = ConfigDict(extra="forbid")

    dx: float = Field(0.0, allow_inf_nan=False)
    dy: float = Field(0.0, allow_inf_nan=False)
    dz: float = Field(0.0, allow_inf_nan=False)
    dyaw: float = Field(0.0, allow_inf_nan=False)


class LinkIn(BaseModel):
    """A manual link: experience ``from`` of this map to experience ``to`` (of ``to_map`` when given)."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    source: int = Field(alias="from", ge=0, le=MAX_ID, description="experience id in this map")
    target: int = Field(alias="to", ge=0, le=MAX_ID, description="experience id in this map, or in to_map")
    to_map: str | None = Field(None, min_length=1, max_length=200, description="another map, merged into this one")
    transform: TransformIn = Field(default_factory=TransformIn)


def author_of(token: TokenRecord) -> str:
    """Return the author a token's link is stored with: ``token ID`` and its label when it has one."""
    return f"token {token.id}" + (f" ({token.label})" if token.label else "")


@router.post("/{name}/links", operation_id="add_link", status_code=201, responses=WRITE_ERRORS)
async def add_link(
    name: MapName, body: Annotated[LinkIn, Body()], services: ServicesDep, token: WriteAccess
) -> dict[str, Any]:
    """Add a manual link (201); ``active`` false and ``flagged`` true: it contradicts the map (kept, switched off)."""
    t = body.transform
    request = LinkRequest(map_name=name, from_id=body.source, to_id=body.target, to_map=body.to_map,
                          transform=(t.dx, t.dy, t.dz, t.dyaw), author=author_of(token))  # fmt: skip
    outcome = await run_in_threadpool(link_experiences, services.db, request)
    return outcome.as_dict()


def _listed(services: Services, name: str) -> dict[str, Any]:
    with services.db.read() as conn:
        record = get_map(conn=conn, name=name)
        return {"map": record.name, "links": [link.as_dict() for link in manual_links(conn=conn, map_id=record.id)]}


@router.get("/{name}/links", operation_id="list_links", responses=MAP_ERRORS)
async def list_links(name: MapName, services: ServicesDep, _token: ReadAccess) -> dict[str, Any]:
    """List the map's manual links: ends, transform, ``active``, and the event, author and time that added each."""
    return await run_in_threadpool(_listed, services, name)
