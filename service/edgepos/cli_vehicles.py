"""``edgepos vehicles``: manage the vehicle registry of a running server over HTTP (admin key).

    edgepos vehicles import FILE     register every vehicle id of FILE (chunks of 5,000)
    edgepos vehicles register ID     register one vehicle
    edgepos vehicles rotate ID       issue a vehicle a new key (the old one opens nothing from then on)
    edgepos vehicles revoke ID       remove a vehicle: its key opens nothing, its live session ends
    edgepos vehicles list            every registered vehicle, as CSV

FILE is a CSV whose header names a ``vehicle_id`` column (other columns are ignored), or a plain file of
one id per line without a header (when its first line is not ``vehicle_id``). The whole file is checked
before anything is sent: a blank line, an id the server would refuse (1-128 letters, digits, space and
. _ : + @ / -; no leading or trailing space) or an id listed twice is reported with its line number and
nothing is registered (exit 2). Ids already registered are left as they are, keys included.

The keys issued by import, register and rotate are shown once by the server. They go to ``--out`` as a
CSV ``vehicle_id,key`` created with mode 0600 (default ``vehicle-keys.csv``; an existing file is never
overwritten without ``--force``, since it may hold keys shown only once), written chunk by chunk so that
the keys of the chunks registered before a failure are kept; never to the terminal unless ``--out -``.
A refusal by the server or no answer prints one line and exits 1.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import re
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO

from edgepos_client import (
    MAX_VEHICLES_PER_IMPORT,
    VEHICLE_ID_PATTERN,
    EdgeposClient,
    EdgeposError,
    VehicleKey,
)

PROG = "edgepos vehicles"
DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_OUT = "vehicle-keys.csv"
HEADER = "vehicle_id"
MAX_REPORTED_PROBLEMS = 20

_VEHICLE_ID = re.compile(VEHICLE_ID_PATTERN)


class UsageError(Exception):
    """A problem found before anything was sent (exit 2)."""


# -- the ids file -------------------------------------------------------------------------------------
@dataclass
class IdsFile:
    """The ids of an import file, in file order, and every problem found (``line N: ...``)."""

    ids: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    has_header: bool = False


def id_problem(value: str) -> str | None:
    """Why ``value`` cannot be imported as a vehicle id, or None."""
    if not value:
        return "empty vehicle_id"
    if value != value.strip():
        return f"vehicle_id {value!r} has leading or trailing spaces"
    if len(value) > 128:
        return f"vehicle_id {value[:40]!r}... is {len(value)} characters long (at most 128)"
    if _VEHICLE_ID.fullmatch(value) is None:
        bad = "".join(sorted({c for c in value if _VEHICLE_ID.fullmatch(c) is None}))
        return (
            f"vehicle_id {value!r} has characters {bad!r}: only letters, digits, space and . _ : + @ / - "
            "are allowed"
        )
    return None


def _lines(text: str) -> list[str]:
    """The physical lines of ``text`` without their line ends (\\n, \\r\\n or \\r)."""
    return [line.rstrip("\r\n") for line in io.StringIO(text, newline="")]


def parse_ids(text: str) -> IdsFile:
    """The vehicle ids of an import file's text, with the line number of every problem."""
    result = IdsFile()
    lines = _lines(text)
    if not lines:
        result.problems.append("the file is empty")
        return result
    header = next(csv.reader([lines[0]]), [])
    names = [name.strip().lower() for name in header]
    if HEADER in names:
        result.has_header = True
        if names.count(HEADER) > 1:
            times = names.count(HEADER)
            result.problems.append(f"line 1: the header names the {HEADER} column {times} times")
            return result
        rows = _csv_rows(text, names.index(HEADER), len(header), result)
    elif len(header) > 1:
        result.problems.append(
            f"line 1: the header has no {HEADER} column (a CSV needs a header naming its {HEADER} column; "
            "a file of one id per line needs no header)"
        )
        return result
    else:
        rows = ((number, line, None) for number, line in enumerate(lines, start=1))
    seen: dict[str, int] = {}
    for number, value, blank in rows:
        if blank is not None:
            result.problems.append(f"line {number}: {blank}")
            continue
        if not value.strip():
            empty = "empty vehicle_id" if result.has_header else "blank line"
            result.problems.append(f"line {number}: {empty}")
            continue
        problem = id_problem(value)
        if problem is not None:
            result.problems.append(f"line {number}: {problem}")
        elif value in seen:
            result.problems.append(f"line {number}: vehicle_id {value!r} repeats line {seen[value]}")
        else:
            seen[value] = number
            result.ids.append(value)
    if not result.ids and not result.problems:
        result.problems.append("the file lists no vehicle id")
    return result


def _csv_rows(text: str, column: int, width: int, result: IdsFile) -> Iterable[tuple[int, str, str | None]]:
    """(line number, vehicle id, problem or None) of each record after the header."""
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        next(reader)
        start = reader.line_num + 1
        for row in reader:
            number, start = start, reader.line_num + 1
            if not any(cell.strip() for cell in row):
                yield number, "", "blank line"
            elif len(row) <= column:
                yield number, "", f"no {HEADER} field (the row has {len(row)} field(s), the header {width})"
            else:
                yield number, row[column], None
    except csv.Error as error:
        result.problems.append(f"line {reader.line_num}: not valid CSV ({error})")


def read_ids(path: Path) -> IdsFile:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise UsageError(f"cannot read {path}: {error.strerror or error}") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise UsageError(f"{path}: line {line}: not UTF-8 text") from None
    return parse_ids(text)


# -- the keys file ------------------------------------------------------------------------------------
class KeysOut:
    """Where issued keys go: a new CSV file created with mode 0600, or stdout for ``-``.

    Opened before anything is sent, so a key is never issued with nowhere to write it; rows are flushed
    to disk as they come. An existing file is refused unless ``force``; then the keys go to a new file
    beside it that replaces it once a key is written, so a failed call leaves the old file as it was. A
    file that received no key is removed."""

    def __init__(self, target: str, force: bool) -> None:
        self.target = target
        self.count = 0
        self._stream: IO[str]
        self.path: Path | None = None
        self._writing: Path | None = None
        if target == "-":
            self._stream = sys.stdout
        else:
            self.path = Path(target)
            replacing = force and (self.path.exists() or self.path.is_symlink())
            self._writing = (
                self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp") if replacing else self.path
            )
            flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
            try:
                descriptor = os.open(self._writing, flags, 0o600)
            except FileExistsError:
                raise UsageError(
                    f"{target} exists and may hold keys the server showed only once: choose another --out, "
                    "or give --force to overwrite it"
                ) from None
            except OSError as error:
                raise UsageError(f"cannot create {target}: {error.strerror or error}") from None
            os.fchmod(descriptor, 0o600)  # whatever the umask
            self._stream = os.fdopen(descriptor, "w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._stream, lineterminator="\n")
        self._writer.writerow(["vehicle_id", "key"])

    @property
    def where(self) -> str:
        return "stdout" if self.path is None else f"{self.target} (mode 0600)"

    def write(self, keys: Iterable[VehicleKey]) -> None:
        for key in keys:
            self._writer.writerow([key.vehicle_id, key.key])
            self.count += 1
        self._stream.flush()
        if self.path is None:
            return
        os.fsync(self._stream.fileno())
        if self.count and self._writing != self.path:
            assert self._writing is not None
            os.replace(self._writing, self.path)  # the open file keeps receiving the next chunks' keys
            self._writing = self.path

    def close(self) -> None:
        if self.path is None or self._writing is None:
            self._stream.flush()
            return
        self._stream.close()
        if self.count == 0:
            self._writing.unlink(missing_ok=True)


# -- actions ------------------------------------------------------------------------------------------
def _say(line: str, keys: KeysOut | None = None) -> None:
    """A report line: on stdout, unless the keys go there."""
    stream = sys.stderr if keys is not None and keys.path is None else sys.stdout
    print(line, file=stream, flush=True)


def _unwritten(keys: KeysOut, error: OSError) -> str:
    return (
        f"cannot write the issued keys to {keys.target}: {error.strerror or error}; the vehicles registered "
        "by the last request have keys nobody holds: issue them new ones with 'edgepos vehicles rotate ID'"
    )


def _import(client: EdgeposClient, args: argparse.Namespace) -> int:
    parsed = read_ids(Path(args.file))
    if parsed.problems:
        for problem in parsed.problems[:MAX_REPORTED_PROBLEMS]:
            print(f"{args.file}: {problem}", file=sys.stderr)
        more = len(parsed.problems) - MAX_REPORTED_PROBLEMS
        if more > 0:
            print(f"{args.file}: ... and {more} more problem(s)", file=sys.stderr)
        total = len(parsed.problems)
        print(f"{PROG}: {args.file} has {total} problem(s); nothing was registered", file=sys.stderr)
        return 2
    chunks = -(-len(parsed.ids) // MAX_VEHICLES_PER_IMPORT)
    keys = KeysOut(args.out, args.force)
    already = 0
    try:
        for number, result in enumerate(client.import_vehicle_chunks(parsed.ids), start=1):
            keys.write(result.registered)
            already += len(result.already_registered)
            if chunks > 1:
                print(
                    f"{PROG}: chunk {number}/{chunks}: registered {len(result.registered)}, "
                    f"already registered {len(result.already_registered)}",
                    file=sys.stderr,
                    flush=True,
                )
    except EdgeposError as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        if keys.count:
            print(
                f"{PROG}: registered {keys.count} before the failure (already registered {already}); "
                f"their keys are in {keys.where}; importing the file again skips them",
                file=sys.stderr,
            )
        return 1
    except OSError as error:
        print(f"{PROG}: {_unwritten(keys, error)}", file=sys.stderr)
        return 1
    finally:
        keys.close()
    written = f"keys written to {keys.where}" if keys.count else "no keys issued, nothing written"
    _say(f"registered {keys.count}, already registered {already} (left unchanged), {written}", keys)
    return 0


def _issue(client: EdgeposClient, args: argparse.Namespace, rotate: bool) -> int:
    problem = id_problem(args.vehicle_id)
    if problem is not None:
        raise UsageError(problem)
    keys = KeysOut(args.out, args.force)
    try:
        call = client.rotate_vehicle_key if rotate else client.register_vehicle
        issued = call(args.vehicle_id)
        keys.write([issued])
    except EdgeposError as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        return 1
    except OSError as error:
        print(f"{PROG}: {_unwritten(keys, error)}", file=sys.stderr)
        return 1
    finally:
        keys.close()
    if rotate:
        old = "its old key opens nothing now"
        _say(f"issued {issued.vehicle_id!r} a new key ({old}), key written to {keys.where}", keys)
    else:
        _say(f"registered {issued.vehicle_id!r}, key written to {keys.where}", keys)
    return 0


def _revoke(client: EdgeposClient, args: argparse.Namespace) -> int:
    revoked = client.revoke_vehicle(args.vehicle_id)
    ended = (
        f"ended its live session {revoked.ended_session}"
        if revoked.ended_session
        else "it had no live session"
    )
    print(f"revoked {revoked.vehicle_id!r}: its key opens nothing now; {ended}")
    return 0


def _time(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, UTC).isoformat(timespec="seconds")


def _list(client: EdgeposClient, args: argparse.Namespace) -> int:
    writer = csv.writer(sys.stdout, lineterminator="\n")
    writer.writerow(["vehicle_id", "created_at", "key_issued_at"])
    count = 0
    for vehicle in client.iter_vehicles(limit=1000):
        writer.writerow([vehicle.vehicle_id, _time(vehicle.created_at), _time(vehicle.key_issued_at)])
        count += 1
    sys.stdout.flush()
    print(f"{PROG}: {count} vehicle(s) registered", file=sys.stderr)
    return 0


# -- command line -------------------------------------------------------------------------------------
def _connection_options(parser: argparse.ArgumentParser) -> None:
    """--url, --admin-key, --admin-key-file and --timeout, accepted before or after the action (their
    defaults are resolved in :func:`run`, so that one given after the action is not overwritten)."""
    parser.add_argument(
        "--url",
        default=argparse.SUPPRESS,
        help=f"base URL of the server (default: $EDGEPOS_URL or {DEFAULT_URL})",
    )
    parser.add_argument(
        "--admin-key", default=argparse.SUPPRESS, help="the server's admin key (default: $EDGEPOS_ADMIN_KEY)"
    )
    parser.add_argument(
        "--admin-key-file",
        default=argparse.SUPPRESS,
        metavar="FILE",
        help="read the admin key from FILE, e.g. edgepos-admin.key written by a server that generated "
        "its key (keeps the key off the command line)",
    )
    parser.add_argument(
        "--timeout", type=float, default=argparse.SUPPRESS, help="seconds per request attempt (default 60)"
    )


def _out_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        default=DEFAULT_OUT,
        metavar="FILE",
        help="CSV file (vehicle_id,key) the issued keys go to, created with mode 0600 "
        f"(default {DEFAULT_OUT}); '-' for stdout",
    )
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.description = (__doc__ or "").replace("``", "")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    _connection_options(parser)
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    importing = actions.add_parser(
        "import",
        help="register every vehicle id of a file",
        description="Register every vehicle id of FILE: a CSV with a header naming a vehicle_id column, "
        "or one id per line without header. The file is checked whole before anything is sent; ids already "
        "registered are left unchanged.",
    )
    importing.add_argument("file", metavar="FILE", help="CSV with a vehicle_id column, or one id per line")
    register = actions.add_parser("register", help="register one vehicle and issue its key")
    register.add_argument("vehicle_id", metavar="ID")
    rotate = actions.add_parser(
        "rotate", help="issue a vehicle a new key; the old one opens nothing from then on"
    )
    rotate.add_argument("vehicle_id", metavar="ID")
    revoke = actions.add_parser(
        "revoke", help="remove a vehicle: its key opens nothing, its live session ends"
    )
    revoke.add_argument("vehicle_id", metavar="ID")
    listing = actions.add_parser("list", help="every registered vehicle as CSV (never a key)")
    for sub in (importing, register, rotate):
        _out_options(sub)
    for sub in (importing, register, rotate, revoke, listing):
        _connection_options(sub)


def _admin_key(args: argparse.Namespace) -> str:
    given = getattr(args, "admin_key", None)
    if given:
        return str(given)
    key_file = getattr(args, "admin_key_file", None)
    if key_file:
        try:
            key = Path(key_file).read_text().strip()
        except OSError as error:
            raise UsageError(f"cannot read --admin-key-file {key_file}: {error.strerror or error}") from None
        if not key:
            raise UsageError(f"--admin-key-file {key_file} is empty")
        return key
    from_environment = os.environ.get("EDGEPOS_ADMIN_KEY")
    if from_environment:
        return from_environment
    raise UsageError(
        "the vehicle registry needs the admin key: give --admin-key or --admin-key-file, or set "
        "EDGEPOS_ADMIN_KEY (a server that generated its key saved it to edgepos-admin.key)"
    )


def run(args: argparse.Namespace) -> int:
    try:
        key = _admin_key(args)
        url = getattr(args, "url", None) or os.environ.get("EDGEPOS_URL") or DEFAULT_URL
        timeout = getattr(args, "timeout", 60.0)
        if not timeout > 0:
            raise UsageError("--timeout must be > 0")
        with EdgeposClient(url, key, timeout=timeout) as client:
            if args.action == "import":
                return _import(client, args)
            if args.action in ("register", "rotate"):
                return _issue(client, args, rotate=args.action == "rotate")
            if args.action == "revoke":
                return _revoke(client, args)
            return _list(client, args)
    except (UsageError, ValueError) as error:  # ValueError: an argument the client refused before sending
        print(f"{PROG}: {error}", file=sys.stderr)
        return 2
    except EdgeposError as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        return 1
