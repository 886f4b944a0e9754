"""How a server process starts and owns its database: the server lock, the listening socket, the run.

One embedded-engine server per SQLite database: :class:`ServerLock` holds an exclusive ``flock`` on a file
next to the database (``<db file>.server-lock``) for the life of the server. A second server on the same
database is refused at start with one line naming the holder; the kernel drops the lock of a process that
dies (even by ``kill -9``), so the next server takes a dead server's lock over without any cleanup. The
file stays on disk (removing it could let two servers lock two different files); its content names the
last holder. PostgreSQL databases and Celery workers need no such lock: several servers on one database are
replicas, kept apart by job leases and fencing tokens (:mod:`mapserver.api.jobengine`).

:func:`claim_server` and :func:`serve_forever` are ``mapserver serve``: take the lock, bind and listen on
the port (a taken port is refused here, before the application starts), then start the application on
that socket — so the job engine's recovery of interrupted jobs runs only in a server that holds its port.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import socket
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from mapserver.api.settings import Settings
from mapserver.errors import ConflictError, StoreError
from mapserver.store.db import sqlite_database_file

logger = logging.getLogger(__name__)

LOCK_SUFFIX = ".server-lock"


class ServerLock:
    """An exclusive, non-blocking ``flock`` on ``path``, held until :meth:`release` or the process's end."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    @classmethod
    def for_settings(cls, settings: Settings) -> ServerLock | None:
        """Return the lock a server with these settings must hold (None: PostgreSQL, Celery jobs, in-memory)."""
        if settings.jobs != "embedded":
            return None
        database = sqlite_database_file(settings.db_url)
        if database is None:
            return None
        return cls(database.with_name(database.name + LOCK_SUFFIX))

    @property
    def held(self) -> bool:
        """Return whether this object holds the lock."""
        return self._fd is not None

    def acquire(self) -> None:
        """Take the lock, or refuse with one line naming the server that holds it.

        Raises:
            ConflictError: another live process holds the lock.
            StoreError: the lock file cannot be created.
        """
        if self._fd is not None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            msg = f"cannot create the server lock file {str(self.path)!r}: {err.strerror or err}"
            raise StoreError(msg) from err
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "another process"
            os.close(fd)
            database = self.path.name.removesuffix(LOCK_SUFFIX)
            msg = (
                f"another mapserver server ({holder}) runs the embedded job engine on {database!r}; stop it first, "
                f"or give this one another --db (lock file {str(self.path)!r})"
            )
            raise ConflictError(msg) from None
        since = datetime.now(UTC).isoformat(timespec="seconds")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}, since {since}\n".encode(), 0)
        self._fd = fd

    def release(self) -> None:
        """Release the lock (idempotent); the file stays, emptied."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def bind_listener(host: str, port: int) -> socket.socket:
    """Return a TCP socket bound to ``host:port`` and listening.

    Raises:
        ConflictError: the address is taken (another server?) or cannot be bound.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # proto IPPROTO_TCP: asyncio turns Nagle's algorithm off (TCP_NODELAY) only on such listeners' connections;
    # with it on, a response's second write waited for the client's delayed ACK, 40 ms a request
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        sock.listen(2048)
    except OSError as err:
        sock.close()
        msg = f"cannot listen on {host}:{port}: {err.strerror or err} (another server on this port? see --port)"
        raise ConflictError(msg) from None
    return sock


@dataclass
class ServerClaim:
    """What a server holds before its application starts: the database's server lock (if any) and its socket."""

    lock: ServerLock | None
    sock: socket.socket

    def release(self) -> None:
        """Close the socket and release the lock."""
        self.sock.close()
        if self.lock is not None:
            self.lock.release()


def claim_server(settings: Settings) -> ServerClaim:
    """Take the database's server lock (SQLite with embedded jobs), then bind and listen on the port.

    Raises:
        ConflictError: another server holds the lock, or the port is taken (one line each).
    """
    lock = ServerLock.for_settings(settings)
    if lock is not None:
        lock.acquire()
    try:
        sock = bind_listener(settings.host, settings.port)
    except BaseException:
        if lock is not None:
            lock.release()
        raise
    return ServerClaim(lock, sock)


def serve_forever(settings: Settings, claim: ServerClaim, *, log_level: str) -> None:
    """Run the application on the claimed socket until the server is stopped; release the claim then.

    The application's lifespan (database, leftovers, job engine and its recovery) starts only now, in a
    process that holds the port and, for SQLite, the database's server lock.
    """
    import uvicorn

    from mapserver.api.app import create_app

    try:
        config = uvicorn.Config(
            create_app(settings, server_lock=claim.lock), host=settings.host, port=settings.port,
            log_level=log_level, timeout_graceful_shutdown=30,
        )  # fmt: skip
        uvicorn.Server(config).run(sockets=[claim.sock])
    finally:
        claim.release()
