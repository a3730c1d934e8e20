"""`greyfit keys`: the service's named API keys (service/http/clients.py), in the job store the server uses."""
from __future__ import annotations

import sys
import time
from pathlib import Path


def add_keys(sub) -> None:
    p = sub.add_parser("keys", help="add, list or revoke the service's API keys (one per client)",
                       description="Manage the named API keys of `greyfit serve`, kept hashed in its job store "
                                   "(GREYFIT_DATABASE_URL, else the SQLite store in --data-dir). Each client sees "
                                   "only its own jobs; a revoked key is refused at once by every server.")
    p.add_argument("--data-dir", default=None, help="the server's data folder (default: GREYFIT_DATA_DIR or ./data)")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION", help="add, list or revoke")
    p_add = actions.add_parser("add", help="make a key for a new client; the key is printed once, on stdout")
    p_add.add_argument("name", help="the client's name: 1 to 64 letters, digits, '.', '_' or '-'")
    actions.add_parser("list", help="the keys' names, when each was made and revoked (never a key)")
    p_revoke = actions.add_parser("revoke", help="refuse a client's key from now on (its jobs stay, unseen)")
    p_revoke.add_argument("name")
    p.set_defaults(func=cmd_keys)


def cmd_keys(args) -> int:
    from greyfit.service.http.clients import KeyRefused, KeyStore
    from greyfit.service.jobs.store import make_engine
    from greyfit.service.settings import Settings
    settings = Settings(data_dir=Path(args.data_dir)) if args.data_dir else Settings()
    engine = make_engine(settings.resolved_database_url())
    try:
        keys = KeyStore(engine)
        if args.action == "add":
            print(keys.add(args.name))
            print(f"greyfit keys: the key of {args.name!r} above is shown this once and stored only hashed: "
                  "hand it to the client (Authorization: Bearer <key>)", file=sys.stderr)
        elif args.action == "revoke":
            keys.revoke(args.name)
            print(f"greyfit keys: {args.name!r} revoked", file=sys.stderr)
        else:
            for row in keys.entries():
                revoked = f"revoked {_when(row['revoked_at'])}" if row["revoked_at"] else "active"
                print(f"{row['name']}\tmade {_when(row['created_at'])}\t{revoked}")
    except KeyRefused as exc:
        print(f"greyfit keys: {exc}", file=sys.stderr)
        return 2
    finally:
        engine.dispose()
    return 0


def _when(at: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(at))
