"""``mapserver token create|list|revoke --db URL``: API tokens (stored as SHA-256 only)."""

from __future__ import annotations

import argparse
import sys

from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, open_database
from mapserver.store.models import TOKEN_SCOPES
from mapserver.store.tokens import create_token, list_tokens, revoke_token


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``token`` command and its ``create``, ``list`` and ``revoke`` subcommands."""
    parser = subparsers.add_parser("token", help="manage REST API tokens")
    actions = parser.add_subparsers(dest="token_action", required=True, metavar="ACTION")
    create = actions.add_parser("create", help="create a token (printed once; only its hash is stored)")
    create.add_argument("--scope", required=True, choices=TOKEN_SCOPES, help="read, or write (includes read)")
    create.add_argument("--label", help="a note saying who or what uses the token")
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
    with open_database(args.db) as db, db.write() as conn:
        token, record = create_token(conn=conn, scope=args.scope, label=args.label)
    info(f"created {record.scope} token {record.id} ({record.prefix}…); keep it: it is not shown again")
    if args.json:
        emit_json({"token": token, "scope": record.scope, "id": record.id})
    else:
        sys.stdout.write(token + "\n")
    return 0


def run_list(args: argparse.Namespace) -> int:
    """List the tokens."""
    with open_database(args.db) as db, db.read() as conn:
        records = list_tokens(conn=conn)
    items = [
        {"id": r.id, "prefix": r.prefix, "scope": r.scope, "label": r.label, "created_at": r.created_at.isoformat(),
         "revoked": r.revoked_at is not None}
        for r in records
    ]  # fmt: skip
    if args.json:
        emit_json({"tokens": items})
        return 0
    for item in items:
        state = "revoked" if item["revoked"] else "active"
        sys.stdout.write(f"{item['id']:>4}  {item['prefix']}…  {item['scope']:<5}  {state:<7}  {item['label'] or ''}\n")
    return 0


def run_revoke(args: argparse.Namespace) -> int:
    """Revoke a token."""
    with open_database(args.db) as db, db.write() as conn:
        revoke_token(conn=conn, token_id=args.token_id)
    info(f"revoked token {args.token_id}")
    if args.json:
        emit_json({"revoked": args.token_id})
    return 0
