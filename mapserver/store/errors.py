"""Store-specific members of the mapserver exception family (see :mod:`mapserver.errors`)."""

from __future__ import annotations

from mapserver.errors import ConflictError, NotFoundError, StoreError


class UnknownMapError(NotFoundError):
    """No stored map has this name or id (exit 2, HTTP 404)."""


class MapExistsError(ConflictError):
    """A map with this name already exists (HTTP 409)."""


class StaleMapError(ConflictError):
    """The map changed since it was read (another writer committed first); nothing was written."""


class OwnershipError(ConflictError):
    """A template or experience in the state being saved is held by another map."""


class CorruptStateError(StoreError):
    """A stored map state is inconsistent (row counts or arrays disagree with its manifest)."""
