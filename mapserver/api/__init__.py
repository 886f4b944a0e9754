"""The REST API (FastAPI): uploads, background jobs, maps and paths. Contract: ``interfaces.md``.

Public surface::

    from mapserver.api import Settings, create_app
    app = create_app(Settings(db_url="sqlite:///./var/mapserver.db", allow_anonymous_reads=True))
    # uvicorn.run(app, host="127.0.0.1", port=8000)  — ``mapserver serve`` binds the port first:
    # lifecycle.serve_forever

Modules: ``app`` (factory), ``settings``, ``deps`` (services and token access), ``errors`` (the one
place errors become responses), ``schemas``, ``routes/`` (one router per resource), ``uploads``
(streaming multipart), ``archives`` (safe unpacking), ``intake`` (upload → checked log),
``jobengine`` (the job engine protocol and the embedded thread pool), ``worker`` (one job through
the pipeline), ``graphs`` (cached path graphs), ``lifecycle`` (the server lock, binding, running),
``housekeeping`` (leftover and expired uploads).
"""

from mapserver.api.app import create_app
from mapserver.api.jobengine import EmbeddedJobEngine, JobEngine
from mapserver.api.settings import Settings

__all__ = ["EmbeddedJobEngine", "JobEngine", "Settings", "create_app"]
