"""Friendly failures (issue #19): every command fed a missing file, an empty file, a file of the wrong
format or a folder where a file is expected answers with one line on stderr and exit status 2, never
a traceback. The commands are read from the parser, so a new command without a case fails here."""

from __future__ import annotations

import argparse

import pytest

from hybridloc.cli import build_parser, main


def _leaves(p: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path)
        return
    for a in subs:
        for name, sp in a.choices.items():
            yield from _leaves(sp, (*path, name))


# command -> argv with {f} the bad input and {o} an output folder. Commands with no input file of
# their own get it as the settings file (--config), which every command reads first.
CASES: dict[str, list[str]] = {
    "data inspect": ["data", "inspect", "{f}"],
    "pdr phone": ["pdr", "phone", "{f}", "--out", "{o}"],
    "pdr foot": ["pdr", "foot", "{f}", "--out", "{o}"],
    "map build": ["map", "build", "{f}", "--format", "msft", "--out", "{o}/m.npz"],
    "map show": ["map", "show", "{f}", "--out", "{o}/m.png"],
    "map import": ["map", "import", "{f}", "--site", "s", "--db", "{o}/h.db"],
    "map export": ["--config", "{f}", "map", "export", "--site", "s", "--db", "{o}/h.db", "--out", "{o}/m.npz"],
    "map rebuild": ["--config", "{f}", "map", "rebuild", "--site", "s", "--db", "{o}/h.db"],
    "client phone": ["client", "phone", "--site", "s", "--replay", "{f}", "--spool", "{o}/spool"],
    "client foot": ["client", "foot", "--site", "s", "--replay", "{f}", "--spool", "{o}/spool"],
    "client survey": ["client", "survey", "--site", "s", "--replay", "{f}", "--spool", "{o}/spool"],
    "serve": ["--config", "{f}", "serve", "--db", "{o}/h.db"],
    "dashboard": ["--config", "{f}", "dashboard", "--db", "{o}/h.db", "--http", "127.0.0.1:0"],
    "db upgrade": ["--config", "{f}", "db", "upgrade", "--db", "{o}/h.db"],
    "status": ["--config", "{f}", "status", "--timeout", "0.1"],
    "locate": ["locate", "{f}", "--map", "{f}", "--format", "msft", "--out", "{o}"],
    "sim world": ["sim", "world", "--seed", "1", "--floorplan", "{f}", "--out", "{o}/w"],
    "sim walk": ["sim", "walk", "--world", "{f}", "--out", "{o}/w"],
    "eval pdr-phone": ["eval", "pdr-phone", "{f}"],
    "eval pdr-foot": ["eval", "pdr-foot", "{f}"],
    "eval fingerprint": ["eval", "fingerprint", "--uji", "{f}", "--ilc", ""],
    "eval sim-realism": ["eval", "sim-realism", "--ilc", "{f}"],
    "eval fusion": ["eval", "fusion", "{f}", "--out", "{o}"],
    "eval slam": ["eval", "slam", "{f}", "--workers", "1"],
    "eval crowd": ["eval", "crowd", "{f}", "--out", "{o}"],
    "floorplan import": ["floorplan", "import", "{f}", "--site", "s", "--db", "{o}/h.db"],
    "floorplan export": ["--config", "{f}", "floorplan", "export", "--site", "s", "--db", "{o}/h.db", "--out", "{o}/p.geojson"],
    "slam run": ["slam", "run", "{f}", "--out", "{o}/slam", "--workers", "1"],
    "slam show": ["slam", "show", "{f}", "--floor", "F1", "--out", "{o}/s.png"],
    "slam rebuild": ["slam", "rebuild", "--db", "{f}"],
    "demo": ["--config", "{f}", "demo", "--out", "{o}"],
}

# not a recording, a radio map, a MATLAB file, a CSV of any known layout, nor TOML
WRONG = "<html><body>not a recording</body></html>\n= = [ nothing here\n"


def test_every_command_has_a_case():
    assert set(_leaves(build_parser())) == set(CASES)


@pytest.mark.parametrize("kind", ["missing", "empty", "wrong", "folder"])
@pytest.mark.parametrize("command", sorted(CASES))
def test_bad_input_is_one_line_and_exit_2(command, kind, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing a command might write lands in the checkout
    for var in ("HYBRIDLOC_CONFIG",):
        monkeypatch.delenv(var, raising=False)
    f = tmp_path / f"input-{kind}"
    if kind == "empty":
        f.write_bytes(b"")
    elif kind == "wrong":
        f.write_text(WRONG)
    elif kind == "folder":
        f.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    argv = [a.replace("{f}", str(f)).replace("{o}", str(out)) for a in CASES[command]]
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse
        rc = exc.code
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, (rc, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    "option, value, says",
    [
        ("--slam-processes", "-1", "--slam-processes must be >= 0"),
        ("--slam-batch-share", "11", "--slam-batch-share must be a share"),
        ("--slam-batch-every", "-2", "--slam-batch-every must be >= 0"),
        ("--slam-idle", "-5", "--slam-idle must be >= 0"),
        ("--ingest-workers", "-1", "--ingest-workers must be >= 0"),
        ("--locate-workers", "-3", "--locate-workers must be >= 0"),
    ],
)
def test_serve_refuses_bad_slam_options_before_it_starts(option, value, says, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HYBRIDLOC_CONFIG", raising=False)
    try:
        rc = main(["serve", "--db", str(tmp_path / "h.db"), "--site", "s1", option, value])
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2 and says in err and len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert not (tmp_path / "h.db").exists()  # refused before the server opened anything


def test_serve_refuses_a_grown_map_for_the_cell_likelihood(tmp_path, capsys, monkeypatch):
    """--slam-grow-map serves walks' labels to the kNN locator; with --method prob: exit 2, one line, nothing opened."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HYBRIDLOC_CONFIG", raising=False)
    try:
        rc = main(["serve", "--db", str(tmp_path / "h.db"), "--site", "s1", "--method", "prob", "--slam-grow-map"])
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2 and "--slam-grow-map" in err and len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert not (tmp_path / "h.db").exists()


def test_eval_crowd_refuses_a_grown_map_without_slam(tmp_path, capsys):
    try:
        rc = main(["eval", "crowd", str(tmp_path), "--no-slam", "--grow-map", "--out", str(tmp_path / "out")])
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2 and "--grow-map needs the crowd SLAM" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


def test_serve_on_an_endpoint_in_use_says_so_in_one_line(tmp_path, capsys, monkeypatch):
    """A second server on a listening endpoint: exit 2 and one line naming the endpoint, no traceback."""
    from hybridloc.server.service import Server
    from hybridloc.wire.zconfig import free_port

    monkeypatch.delenv("HYBRIDLOC_CONFIG", raising=False)
    ep = f"tcp/127.0.0.1:{free_port()}"
    with Server(ep, str(tmp_path / "a.db")):
        rc = main(["serve", "--endpoint", ep, "--db", str(tmp_path / "b.db"), "--ingest-workers", "0"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and ep in err and "in use" in err and "Traceback" not in err, err


def test_status_with_no_server_says_so_in_one_line(capsys, monkeypatch):
    """Nothing listening at the endpoint: exit 2 and one line naming it, Zenoh's reason without its
    source paths, no traceback."""
    from hybridloc.wire.zconfig import free_port

    monkeypatch.delenv("HYBRIDLOC_CONFIG", raising=False)
    ep = f"tcp/127.0.0.1:{free_port()}"
    rc = main(["status", "--endpoint", ep, "--timeout", "0.5"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and f"cannot reach the server at {ep}" in err, err
    assert "Traceback" not in err and ".cargo" not in err and "password" not in err, err
    # with credentials, Zenoh's "Unable to connect" may also be a refused login: the line says so
    assert main(["status", "--endpoint", ep, "--timeout", "0.5", "--user", "dev01", "--password", "pw"]) == 2
    assert "a wrong user, password or CA reads the same" in capsys.readouterr().err


def test_a_per_file_error_names_the_file_once_with_its_line(tmp_path, capsys):
    """``FILE:LINE: error: ...`` (the usual form), not the file named twice."""
    bad = tmp_path / "g.csv"
    bad.write_text("garbage,1,2\n")
    assert main(["pdr", "phone", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"{bad}:1: error: unknown format") and err.count(str(bad)) == 1, err
    assert main(["pdr", "phone", str(tmp_path / "none.txt"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"{tmp_path / 'none.txt'}: error: no such recording", err
