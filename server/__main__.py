"""Command line: ``python -m server serve|migrate|keys ...``."""

from __future__ import annotations

import argparse
import sys

from server import migrate as migrations
from server.auth import SCOPES, create_key
from server.config import get_settings
from server.db import Database
from server.store import keys as store


def _int_in(low: int, high: int | None = None):
    """An argparse type: an integer in [low, high], else a usage error naming the value (uvicorn took
    ``--port 70000`` for another port and ``--log-level loud`` with a traceback)."""
    what = f"an integer ≥ {low}" + ("" if high is None else f" and ≤ {high}")

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {what}, not {text!r}")
        return value

    return parse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server", description="Indoor positioning service.")
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="apply pending migrations, then run the HTTP server")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=_int_in(1, 65535), default=8000)
    serve.add_argument("--workers", type=_int_in(1), default=1, help="server processes (share the database)")
    serve.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug", "trace"))

    commands.add_parser("migrate", help="apply pending database migrations and exit")
    commands.add_parser("worker", help="train queued models (for servers run with LOCALIZER_EMBEDDED_WORKER=false)")

    keys = commands.add_parser("keys", help="manage API keys (stored hashed)")
    key_commands = keys.add_subparsers(dest="keys_command", required=True)
    create = key_commands.add_parser("create", help="create a key and print it once")
    create.add_argument("--scope", choices=SCOPES, required=True)
    create.add_argument("--name", required=True, help="who or what the key is for")
    revoke = key_commands.add_parser("revoke", help="revoke a key by id")
    revoke.add_argument("id", type=int)
    key_commands.add_parser("list", help="list keys (never their values)")

    args = parser.parse_args(argv)
    settings = get_settings()
    migrations.upgrade(settings.database_url)
    if args.command == "serve":
        import uvicorn

        uvicorn.run(
            "server.app:create_app", factory=True, host=args.host, port=args.port,
            workers=args.workers, log_level=args.log_level,
        )
    elif args.command == "worker":
        from server.services.training import TrainingWorker

        worker = TrainingWorker(settings.database_url, settings.training_poll_s, settings.training_stale_after_s)
        try:
            worker.serve_forever()
        except KeyboardInterrupt:
            worker.stop()
    elif args.command == "keys":
        return _keys(Database(settings.database_url), args)
    return 0


def _keys(db: Database, args: argparse.Namespace) -> int:
    if args.keys_command == "create":
        key_id, key = create_key(db, args.name, args.scope)
        print(f"created {args.scope} key {key_id} for {args.name!r}; store it now, it is not shown again:")
        print(key)
        return 0
    with db.transaction() as s:
        if args.keys_command == "revoke":
            if not store.revoke_api_key(s, args.id):
                print(f"no active key with id {args.id}", file=sys.stderr)
                return 1
            print(f"revoked key {args.id}")
            return 0
        for info in store.list_api_keys(s):
            state = f"revoked {info.revoked_at:%Y-%m-%d %H:%M}" if info.revoked_at else "active"
            print(f"{info.id:>4}  {info.scope:<6}  {state:<24}  {info.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
