"""``edgepos vehicles``: the import file is checked whole before anything is sent, the issued keys go only
to a new mode-0600 file, and import / register / rotate / revoke / list drive a real server process over a
real loopback socket (the import also from a real ``python -m edgepos.cli`` process)."""

from __future__ import annotations

import csv
import io
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from edgepos.cli import main
from edgepos.cli_vehicles import parse_ids
from edgepos.loadgen.localserver import clean_environment, free_port
from edgepos_client import EdgeposClient, Forbidden, NotFound, Unauthorized

# -- the ids file, without a server -----------------------------------------------------------------


def test_csv_with_a_vehicle_id_column() -> None:
    parsed = parse_ids('depot,Vehicle_ID\r\nnorth,bus 1/a\r\n"south, east",bus-2\r\n')
    assert parsed.has_header and parsed.ids == ["bus 1/a", "bus-2"] and parsed.problems == []


def test_plain_file_of_one_id_per_line() -> None:
    parsed = parse_ids("\ufeffbus-1\nfleet/7 bus\n".lstrip("\ufeff"))
    assert not parsed.has_header and parsed.ids == ["bus-1", "fleet/7 bus"] and parsed.problems == []


def test_every_problem_is_named_with_its_line() -> None:
    text = "vehicle_id,model\nbus-1,a\nbus-2,b\nbus-1,c\n\nbus#6,d\n,e\nbus-8\n" + "x" * 129 + "\n bus-9,f\n"
    parsed = parse_ids(text)
    assert parsed.problems == [
        "line 4: vehicle_id 'bus-1' repeats line 2",
        "line 5: blank line",
        (
            "line 6: vehicle_id 'bus#6' has characters '#': only letters, digits, space and . _ : + @ / - "
            "are allowed"
        ),
        "line 7: empty vehicle_id",
        f"line 9: vehicle_id {'x' * 40!r}... is 129 characters long (at most 128)",
        "line 10: vehicle_id ' bus-9' has leading or trailing spaces",
    ]
    plain = parse_ids("a\nb\n\nb\n")
    assert plain.problems == ["line 3: blank line", "line 4: vehicle_id 'b' repeats line 2"]
    assert "no vehicle_id column" in parse_ids("id,name\nbus-1,a\n").problems[0]
    assert parse_ids("").problems == ["the file is empty"]
    assert parse_ids("vehicle_id\n").problems == ["the file lists no vehicle id"]


def test_a_bad_file_exits_2_before_connecting(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    Path("fleet.csv").write_text("vehicle_id\nbus-1\nbus-1\n")
    nowhere = f"http://127.0.0.1:{free_port()}"  # nothing listens: any request would exit 1, not 2
    assert main(["vehicles", "import", "fleet.csv", "--url", nowhere, "--admin-key", "k"]) == 2
    err = capsys.readouterr().err
    assert "fleet.csv: line 3: vehicle_id 'bus-1' repeats line 2" in err and "nothing was registered" in err
    assert not Path("vehicle-keys.csv").exists()


def test_without_an_admin_key_nothing_is_tried(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["vehicles", "list"]) == 2
    assert "needs the admin key" in capsys.readouterr().err


def test_keys_of_chunks_registered_before_a_failure_are_kept(tmp_path: Path, monkeypatch, capsys) -> None:
    """The second of three chunks fails: the first chunk's keys are in the file, the third is never sent."""
    from edgepos import cli_vehicles
    from edgepos_client import _protocol

    monkeypatch.setattr(_protocol, "MAX_VEHICLES_PER_IMPORT", 2)
    bodies: list[list[str]] = []

    def server(request: httpx.Request) -> httpx.Response:
        ids = [item["vehicle_id"] for item in json.loads(request.content)["vehicles"]]
        bodies.append(ids)
        if len(bodies) == 2:
            return httpx.Response(500, json={"error": {"code": "internal_error", "message": "boom"}})
        issued = [{"vehicle_id": i, "key": f"evk_{i}", "created_at": 1.0, "key_issued_at": 1.0} for i in ids]
        return httpx.Response(200, json={"registered": issued, "already_registered": []})

    real = cli_vehicles.EdgeposClient
    monkeypatch.setattr(
        cli_vehicles,
        "EdgeposClient",
        lambda url, key, **options: real(url, key, transport=httpx.MockTransport(server), **options),
    )
    monkeypatch.chdir(tmp_path)
    Path("fleet.txt").write_text("a\nb\nc\nd\ne\n")
    assert main(["vehicles", "import", "fleet.txt", "--admin-key", "k"]) == 1
    assert bodies == [["a", "b"], ["c", "d"]]
    assert read_keys(tmp_path / "vehicle-keys.csv") == {"a": "evk_a", "b": "evk_b"}
    err = capsys.readouterr().err
    assert "500 internal_error: boom" in err
    assert "registered 2 before the failure" in err and "vehicle-keys.csv" in err


# -- against a real server ---------------------------------------------------------------------------
def read_keys(path: Path) -> dict[str, str]:
    rows = list(csv.reader(io.StringIO(path.read_text())))
    assert rows[0] == ["vehicle_id", "key"]
    return dict(rows[1:])


def mode(path: Path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.slow
def test_import_1200_vehicles_then_again(
    server_url: str, admin_key: str, tmp_path: Path, monkeypatch, capsys
) -> None:
    ids = [f"fleet/{n:04d} bus" for n in range(1200)]
    fleet = tmp_path / "fleet.csv"
    fleet.write_text("vehicle_id,depot\n" + "".join(f"{vid},depot-{n % 7}\n" for n, vid in enumerate(ids)))
    environment = clean_environment(EDGEPOS_ADMIN_KEY=admin_key, EDGEPOS_URL=server_url)
    done = subprocess.run(
        [sys.executable, "-m", "edgepos.cli", "vehicles", "import", "fleet.csv"],
        env=environment,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == (
        "registered 1200, already registered 0 (left unchanged), "
        "keys written to vehicle-keys.csv (mode 0600)\n"
    )
    keys_file = tmp_path / "vehicle-keys.csv"
    assert mode(keys_file) == 0o600
    keys = read_keys(keys_file)
    assert list(keys) == ids and all(key.startswith("evk_") for key in keys.values())
    assert len(set(keys.values())) == 1200
    assert "evk_" not in done.stdout + done.stderr  # keys go to the file only

    with EdgeposClient(server_url, vehicle_key=keys[ids[7]]) as car:
        assert car.create_session(ids[7]).vehicle_id == ids[7]
        with pytest.raises(Forbidden):
            car.create_session(ids[8])
    with EdgeposClient(server_url, admin_key) as admin:
        assert {v.vehicle_id for v in admin.iter_vehicles()} >= set(ids)

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("EDGEPOS_URL", server_url)
    monkeypatch.setenv("EDGEPOS_ADMIN_KEY", admin_key)
    before = keys_file.read_bytes()
    assert main(["vehicles", "import", "fleet.csv"]) == 2  # the default --out exists: refused
    assert "--force" in capsys.readouterr().err and keys_file.read_bytes() == before

    assert main(["vehicles", "import", "fleet.csv", "--out", "again.csv"]) == 0
    out = capsys.readouterr().out
    assert out == "registered 0, already registered 1200 (left unchanged), no keys issued, nothing written\n"
    assert not (tmp_path / "again.csv").exists()

    with fleet.open("a") as more:
        more.write("fleet/new 1,x\nfleet/new 2,y\n")
    assert main(["vehicles", "import", str(fleet), "--out", "vehicle-keys-2.csv"]) == 0
    assert capsys.readouterr().out == (
        "registered 2, already registered 1200 (left unchanged), "
        "keys written to vehicle-keys-2.csv (mode 0600)\n"
    )
    assert list(read_keys(tmp_path / "vehicle-keys-2.csv")) == ["fleet/new 1", "fleet/new 2"]


@pytest.mark.slow
def test_bad_files_register_nothing(server_url: str, admin_key: str, tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    base = ["--url", server_url, "--admin-key", admin_key]
    Path("bad.csv").write_text("vehicle_id,model\nbad-1,a\nbad-2,b\nbad-1,c\nbad#4,d\nbad-5,e\n")
    assert main(["vehicles", "import", "bad.csv", *base]) == 2
    err = capsys.readouterr().err
    assert "bad.csv: line 4: vehicle_id 'bad-1' repeats line 2" in err
    assert "bad.csv: line 5: vehicle_id 'bad#4' has characters '#'" in err
    assert "edgepos vehicles: bad.csv has 2 problem(s); nothing was registered" in err
    Path("bad.txt").write_text("plain-1\nplain 2\n\nplain-1\n")
    assert main(["vehicles", "import", "bad.txt", *base]) == 2
    err = capsys.readouterr().err
    assert "bad.txt: line 3: blank line" in err and "line 4: vehicle_id 'plain-1' repeats line 1" in err
    assert main(["vehicles", "import", "missing.csv", *base]) == 2
    assert "cannot read missing.csv" in capsys.readouterr().err
    assert not Path("vehicle-keys.csv").exists()
    with EdgeposClient(server_url, admin_key) as admin:
        for vehicle_id in ("bad-1", "bad-2", "bad-5", "plain-1", "plain 2"):
            with pytest.raises(NotFound):
                admin.get_vehicle(vehicle_id)


@pytest.mark.slow
def test_register_rotate_list_revoke(server_url: str, admin_key: str, tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    key_file = tmp_path / "admin.key"
    key_file.write_text(admin_key + "\n")
    base = ["--url", server_url, "--admin-key-file", str(key_file)]
    vid = "cli/7 bus"

    assert main(["vehicles", "register", vid, "--out", "reg.csv", *base]) == 0
    out = capsys.readouterr().out
    assert out == "registered 'cli/7 bus', key written to reg.csv (mode 0600)\n"
    assert mode(tmp_path / "reg.csv") == 0o600
    first_key = read_keys(tmp_path / "reg.csv")[vid]
    with EdgeposClient(server_url, vehicle_key=first_key) as car:
        first = car.create_session(vid)

    assert main(["vehicles", "register", vid, "--out", "reg2.csv", *base]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "409 conflict" in err and "already registered" in err
    assert not (tmp_path / "reg2.csv").exists()  # no key, no file left behind

    assert main(["vehicles", *base, "rotate", vid, "--out", "-"]) == 0  # options before the action too
    captured = capsys.readouterr()
    new_key = read_keys_text(captured.out)[vid]
    assert new_key != first_key and "a new key" in captured.err and "stdout" in captured.err
    with EdgeposClient(server_url, vehicle_key=first_key) as car, pytest.raises(Unauthorized):
        car.create_session(vid)
    with EdgeposClient(server_url, vehicle_key=new_key) as car:
        second = car.create_session(vid)
    assert second.superseded == first.session_id

    assert main(["vehicles", "list", *base]) == 0
    captured = capsys.readouterr()
    rows = list(csv.reader(io.StringIO(captured.out)))
    assert rows[0] == ["vehicle_id", "created_at", "key_issued_at"]
    row = next(r for r in rows if r[0] == vid)
    assert row[1].endswith("+00:00") and row[2] >= row[1]
    assert [r[0] for r in rows[1:]] == sorted(r[0] for r in rows[1:])
    assert f"{len(rows) - 1} vehicle(s) registered" in captured.err and "evk_" not in captured.out

    assert main(["vehicles", "revoke", vid, *base]) == 0
    assert capsys.readouterr().out == (
        f"revoked 'cli/7 bus': its key opens nothing now; ended its live session {second.session_id}\n"
    )
    with EdgeposClient(server_url, vehicle_key=new_key) as car, pytest.raises(Unauthorized):
        car.create_session(vid)

    assert main(["vehicles", "rotate", vid, "--out", "rot.csv", *base]) == 1
    assert "404 not_found" in capsys.readouterr().err and not (tmp_path / "rot.csv").exists()
    done = subprocess.run(
        [sys.executable, "-m", "edgepos.cli", "vehicles", "revoke", vid, *base],
        env=clean_environment(),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and "404 not_found" in done.stderr and "Traceback" not in done.stderr


def read_keys_text(text: str) -> dict[str, str]:
    rows = list(csv.reader(io.StringIO(text)))
    assert rows[0] == ["vehicle_id", "key"]
    return dict(rows[1:])


@pytest.mark.slow
def test_out_file_never_overwritten_without_force(
    server_url: str, admin_key: str, tmp_path: Path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("EDGEPOS_ADMIN_KEY", admin_key)
    precious = tmp_path / "keys.csv"
    precious.write_text("vehicle_id,key\nold,evk_shown_once\n")
    precious.chmod(0o644)
    assert main(["vehicles", "register", "force-1", "--out", "keys.csv", "--url", server_url]) == 2
    assert "keys.csv exists" in capsys.readouterr().err
    assert precious.read_text() == "vehicle_id,key\nold,evk_shown_once\n"
    with EdgeposClient(server_url, admin_key) as admin, pytest.raises(NotFound):
        admin.get_vehicle("force-1")  # refused before anything was sent

    forced = ["--out", "keys.csv", "--force", "--url", server_url]
    assert main(["vehicles", "rotate", "force-1", *forced]) == 1  # not registered: 404
    assert "404 not_found" in capsys.readouterr().err
    assert precious.read_text() == "vehicle_id,key\nold,evk_shown_once\n"  # a failed call leaves it as it was
    assert main(["vehicles", "register", "force-1", *forced]) == 0
    assert list(read_keys(precious)) == ["force-1"] and mode(precious) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keys.csv"]  # no temporary file left


@pytest.mark.slow
def test_server_errors_are_one_line(server_url: str, tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["vehicles", "list", "--url", server_url, "--admin-key", "not-the-key"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("edgepos vehicles: 401 unauthorized") and err.count("\n") == 1
    nowhere = f"http://127.0.0.1:{free_port()}"
    assert main(["vehicles", "register", "x-1", "--url", nowhere, "--admin-key", "k", "--timeout", "2"]) == 1
    err = capsys.readouterr().err
    assert "connection_error" in err and err.count("\n") == 1
    assert not (tmp_path / "vehicle-keys.csv").exists()
