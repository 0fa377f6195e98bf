"""``miss serve``, ``miss user`` and ``miss audit``: the web system and its accounts."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from miss.server.storage.store import Store


def serve_arguments(serve: argparse.ArgumentParser) -> None:
    """``miss serve``: host, port, data folder and server processes."""
    serve.add_argument("--host", default=None)
    serve.add_argument("--port", type=int, default=None)
    serve.add_argument("--data-dir", default=None)
    serve.add_argument(
        "--processes",
        type=int,
        default=1,
        help="server processes on the one port (more than 1 needs PostgreSQL); "
        "MISS_WORKERS is the jobs each runs at once",
    )


def user_arguments(user: argparse.ArgumentParser) -> None:
    """``miss user add|passwd|...``: the server's accounts, offline."""
    user_sub = user.add_subparsers(dest="user_command", required=True, parser_class=type(user))
    add = user_sub.add_parser("add", help="create an account; the password is read from stdin")
    add.add_argument("name")
    add.add_argument("--admin", action="store_true", help="may see everything and read the audit")
    add.add_argument(
        "--pacs", action="store_true", help="may search, import from and send to the PACS"
    )
    add.add_argument("--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data")
    helps = {
        "passwd": "set an account's password (read from stdin); its logins end",
        "disable": "disable an account: it cannot log in, and its logins end",
        "enable": "enable a disabled account again",
        "grant-pacs": "let an account search, import from and send to the PACS",
        "revoke-pacs": "take an account's PACS permission back",
    }
    usage = user_sub.add_parser("usage", help="disk use of each account against MISS_QUOTA_MB")
    usage.add_argument("--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data")
    for name, text in helps.items():
        change = user_sub.add_parser(name, help=text)
        change.add_argument("name")
        change.add_argument(
            "--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data"
        )


def backup_arguments(backup: argparse.ArgumentParser) -> None:
    """``miss backup``: the folder to copy the data folder into."""
    backup.add_argument("dest", help="a new or empty folder for the backup")
    backup.add_argument("--data-dir", default=None)


def restore_arguments(restore: argparse.ArgumentParser) -> None:
    """``miss restore``: the backup folder to bring back."""
    restore.add_argument("src", help="a folder made by 'miss backup'")
    restore.add_argument("--data-dir", default=None)


def audit_arguments(audit: argparse.ArgumentParser) -> None:
    """``miss audit``: the server's audit log, offline."""
    audit.add_argument("--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data")
    audit.add_argument("--limit", type=int, default=500, help="newest entries (default 500)")
    audit.add_argument("--action", default=None, help="only this action (login, share ...)")
    audit.add_argument("--json", action="store_true", help="one JSON object per line")


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the web system until it is stopped; the exit status."""
    from miss.server.main import serve

    return serve(host=args.host, port=args.port, data_dir=args.data_dir, processes=args.processes)


def _read_password() -> str:
    """The new password: typed twice at a terminal, else the first line of stdin."""
    if sys.stdin.isatty():
        import getpass

        first = getpass.getpass("password: ")
        if getpass.getpass("again: ") != first:
            from miss.errors import BadParameter

            raise BadParameter("the two passwords differ; run the command again.")
        return first
    return sys.stdin.readline().rstrip("\r\n")


def cmd_user(args: argparse.Namespace) -> int:
    """``miss user add|passwd|disable|enable|grant-pacs|revoke-pacs NAME``, ``miss user
    usage``. Every running server process hears of a change within a second
    (``accounts.announce_change``): the ended logins, the taken permission count at their
    next request."""
    from miss.server import accounts, audit
    from miss.server.core.settings import Settings
    from miss.server.storage.private import owner_only
    from miss.server.storage.store import Store

    settings = Settings.from_env(data_dir=args.data_dir)
    owner_only(settings.data_dir, settings.database_url)
    store = Store(settings.data_dir, settings.database_url)
    try:
        store.init_schema()
        if args.user_command == "usage":
            said = _usage_table(store, settings.quota_bytes)
        elif args.user_command == "add":
            user = accounts.create_user(
                store, args.name, _read_password(), is_admin=args.admin, pacs=args.pacs
            )
            said = f"created {'administrator' if user.is_admin else 'user'} {user.name!r}"
            said += " with PACS access" if user.pacs else ""
        elif args.user_command in ("grant-pacs", "revoke-pacs"):
            user = accounts.find_user(store, args.name)
            accounts.set_pacs(store, user.id, args.user_command == "grant-pacs")
            accounts.announce_change(store, user.id)
            audit.record(store, "user_change", "(command line)", user.name,
                         pacs=args.user_command == "grant-pacs")  # fmt: skip
            said = f"{args.user_command}: {user.name!r}"
        else:
            user = accounts.find_user(store, args.name)
            if args.user_command == "passwd":
                accounts.set_password(store, user.id, _read_password())
            else:
                accounts.set_disabled(store, user.id, args.user_command == "disable")
            ended = [] if args.user_command == "enable" else accounts.end_sessions(store, user.id)
            accounts.announce_change(store, user.id, end_rooms=args.user_command != "enable")
            audit.record(store, f"user_{args.user_command}", "(command line)", user.name)
            said = f"{args.user_command}: {user.name!r} ({len(ended)} login(s) ended)"
    finally:
        store.close()
    print(said)
    return 0


def _usage_table(store: Store, quota: int) -> str:
    """Each account's volumes, models and MB on disk, largest first, and the quota."""
    from miss.server.quota import MB, usage

    rows = sorted(usage(store).values(), key=lambda u: (-u.bytes, u.account))
    width = max([7, *(len(u.account) for u in rows)])
    lines = [f"{'account':<{width}}  volumes  models        MB"]
    for u in rows:
        name = u.account or "(nobody)"
        lines.append(f"{name:<{width}}  {u.volumes:>7}  {u.models:>6}  {u.bytes / MB:>8.1f}")
    limit = f"{quota / MB:g} MB each (MISS_QUOTA_MB)" if quota else "none (MISS_QUOTA_MB=0)"
    return "\n".join([*lines, f"quota: {limit}"])


def cmd_audit(args: argparse.Namespace) -> int:
    """Print the audit log's newest entries; the exit status."""
    from miss.server import audit
    from miss.server.core.settings import Settings
    from miss.server.storage.store import Store

    settings = Settings.from_env(data_dir=args.data_dir)
    store = Store(settings.data_dir, settings.database_url)
    try:
        store.init_schema()
        entries = audit.entries(store, args.limit, args.action)
    finally:
        store.close()
    for entry in entries:
        print(json.dumps(entry) if args.json else audit.format_line(entry))
    return 0


def cmd_backup(args: argparse.Namespace) -> int:
    """``miss backup DEST``: the database (online: SQLite's backup API or ``pg_dump``),
    then the volumes and models, each file with its SHA-256 in ``manifest.json``."""
    from miss.server.core.settings import Settings
    from miss.server.storage.backup import backup
    from miss.server.storage.private import owner_only

    settings = Settings.from_env(data_dir=args.data_dir)
    owner_only(settings.data_dir, settings.database_url)  # the copy: 0600 files, 0700 folders
    os.nice(10)  # like the job workers: viewers of the running server come first
    done = backup(settings.data_dir, settings.database_url, args.dest)
    print(
        f"backed up {done.files} files ({done.bytes / 2**20:.1f} MB) and the database "
        f"({done.database_bytes / 2**20:.1f} MB) to {args.dest} in {done.seconds:.1f} s"
    )
    return 0


def cmd_restore(args: argparse.Namespace) -> int:
    """``miss restore SRC``: into an empty data folder (and an empty database)."""
    from miss.server.core.settings import Settings
    from miss.server.storage.backup import restore
    from miss.server.storage.private import UMASK

    settings = Settings.from_env(data_dir=args.data_dir)
    os.umask(UMASK)  # the data folder must be empty: restore makes it, owner-only
    done = restore(args.src, settings.data_dir, settings.database_url)
    print(
        f"restored {done.files} files ({done.bytes / 2**20:.1f} MB) and the database into "
        f"{settings.data_dir} in {done.seconds:.1f} s"
    )
    return 0
