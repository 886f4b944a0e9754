"""``mapserver token create|list|revoke --db URL``: API tokens (stored as SHA-256 only; ``--expires 30d``)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, TOKEN_SCOPES, open_database, utcnow
from mapserver.store.tokens import create_token, list_tokens, parse_duration, revoke_token


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``token`` command and its ``create``, ``list`` and ``revoke`` subcommands."""
    parser = subparsers.add_parser("token", help="manage REST API tokens")
    actions = parser.add_subparsers(dest="token_action", required=True, metavar="ACTION")
    create = actions.add_parser("create", help="create a token (printed once; only its hash is stored)")
    create.add_argument("--scope", required=True, choices=TOKEN_SCOPES, help="read, or write (includes read)")
    create.add_argument("--label", help="a note saying who or what uses the token")
    create.add_argument("--expires", metavar="DURATION",
                        help="the token stops working this long from now: N and a unit s, m, h, d or w (e.g. 30d); "
                             "default: never")  # fmt: skip
    listing = actions.add_parser("list", help="list tokens (prefix, scope, label; never the token)")
    revoke = actions.add_parser("revoke", help="revoke a token by id")
    revoke.add_argument("--id", type=int, required=True, dest="token_id", help="token id (see token list)")
    for sub in (create, listing, revoke):
        sub.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
        sub.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    create.set_defaults(func=run_create)
    listing.set_defaults(func=run_list)
    revoke.set_defaults(func=run_revoke)


def run_create(args: argparse.Namespace) -> int:
    """Create a token and print it (the only time it is shown)."""
    expires_at = None if args.expires is None else utcnow() + parse_duration(args.expires)
    with open_database(args.db) as db, db.write() as conn:
        token, record = create_token(conn=conn, scope=args.scope, label=args.label, expires_at=expires_at)
    expiry = None if record.expires_at is None else record.expires_at.isoformat(timespec="seconds")
    until = "never expires" if expiry is None else f"expires {expiry}"
    info(f"created {record.scope} token {record.id} ({until}); keep it: it is not shown again")
    if args.json:
        emit_json({"token": token, "scope": record.scope, "id": record.id, "expires_at": expiry})
    else:
        sys.stdout.write(token + "\n")
    return 0


def run_list(args: argparse.Namespace) -> int:
    """List the tokens (id, scope, state, expiry, label; never the token)."""
    with open_database(args.db) as db, db.read() as conn:
        records = list_tokens(conn=conn)
    now = utcnow()
    items: list[dict[str, Any]] = [
        {"id": r.id, "prefix": r.prefix, "scope": r.scope, "label": r.label, "created_at": r.created_at.isoformat(),
         "revoked": r.revoked_at is not None,
         "expires_at": None if r.expires_at is None else r.expires_at.isoformat(),
         "expired": r.expires_at is not None and r.expires_at <= now}
        for r in records
    ]  # fmt: skip
    if args.json:
        emit_json({"tokens": items})
        return 0
    for item in items:
        state = "revoked" if item["revoked"] else "expired" if item["expired"] else "active"
        until = item["expires_at"][:19] if item["expires_at"] else "never"
        sys.stdout.write(
            f"{item['id']:>4}  {item['prefix']}…  {item['scope']:<5}  {state:<7}  expires {until:<19}  "
            f"{item['label'] or ''}\n"
        )
    return 0


def run_revoke(args: argparse.Namespace) -> int:
    """Revoke a token."""
    with open_database(args.db) as db, db.write() as conn:
        revoke_token(conn=conn, token_id=args.token_id)
    info(f"revoked token {args.token_id}")
    if args.json:
        emit_json({"revoked": args.token_id})
    return 0
