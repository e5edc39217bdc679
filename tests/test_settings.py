"""hybridloc.settings: one typed settings object from a TOML file and HYBRIDLOC_* variables, with the
precedence option > environment > file > default."""

from __future__ import annotations

import dataclasses

import pytest

from hybridloc.errors import BadInput, DataFormatError, MissingData
from hybridloc.settings import Settings, load_settings

FILE = """
site = "site1"
endpoint = "tcp/10.0.0.5:7447"
db = "from-file.db"

[security]
user = "phone-7"
tls_ca = "ca.pem"

[filter]
kind = "particle"
speed = 0
"""


def test_defaults_are_the_command_lines(monkeypatch):
    s = load_settings(None, {})
    assert s == Settings()
    assert (s.endpoint, s.db, s.method, s.filter.kind, s.filter.speed) == ("tcp/127.0.0.1:7447", "hybridloc.db", "knn", "kalman", 1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.site = "x"  # type: ignore[misc]


def test_file_then_environment(tmp_path):
    f = tmp_path / "hybridloc.toml"
    f.write_text(FILE)
    s = load_settings(f, {})
    assert (s.site, s.endpoint, s.db) == ("site1", "tcp/10.0.0.5:7447", "from-file.db")
    assert (s.security.user, s.security.tls_ca, s.filter.kind, s.filter.speed) == ("phone-7", "ca.pem", "particle", 0.0)
    assert isinstance(s.filter.speed, float)
    env = {"HYBRIDLOC_DB": "from-env.db", "HYBRIDLOC_FILTER_SPEED": "2.5", "HYBRIDLOC_SECURITY_PASSWORD": "pw", "PATH": "/bin"}
    s = load_settings(f, env)
    assert (s.db, s.filter.speed, s.security.password, s.site) == ("from-env.db", 2.5, "pw", "site1")
    # the file may also be named by the environment
    assert load_settings(None, {"HYBRIDLOC_CONFIG": str(f)}).site == "site1"


@pytest.mark.parametrize(
    "text, key",
    [
        ('sight = "x"', "sight"),
        ('[security]\npasword = "x"', "security.pasword"),
        ("endpoint = 7447", "endpoint"),
        ('[filter]\nspeed = "fast"', "filter.speed"),
        ('[filter]\nkind = "magic"', "filter.kind"),
        ('security = "x"', "security"),
        ('method = "nearest"', "method"),
        ("[slam]\nenabled = 1", "slam.enabled"),
        ("[slam]\nbatch_every = 2.5", "slam.batch_every"),
        ('[slam]\nidle_s = "long"', "slam.idle_s"),
        ('ingest_workers = "many"', "ingest_workers"),
        ("ingest_workers = -1", "ingest_workers"),
    ],
)
def test_unknown_keys_and_wrong_types_name_the_key(tmp_path, text, key):
    f = tmp_path / "bad.toml"
    f.write_text(text + "\n")
    with pytest.raises(BadInput, match=key.replace(".", r"\.")):
        load_settings(f, {})


def test_slam_section_from_file_and_environment(tmp_path):
    """The server's crowd-SLAM worker: [slam] enabled (bool), idle_s and interval_s (s), batch_every (walks)."""
    f = tmp_path / "s.toml"
    f.write_text("[slam]\nenabled = false\nidle_s = 60\nbatch_every = 10\n")
    s = load_settings(f, {})
    assert (s.slam.enabled, s.slam.idle_s, s.slam.batch_every, s.slam.batch_share, s.slam.interval_s) == (False, 60.0, 10, 0.0, 3600.0)
    assert load_settings(None, {"HYBRIDLOC_SLAM_BATCH_SHARE": "0.5"}).slam.batch_share == 0.5
    assert isinstance(s.slam.idle_s, float) and isinstance(s.slam.batch_every, int)
    s = load_settings(f, {"HYBRIDLOC_SLAM_ENABLED": "true", "HYBRIDLOC_SLAM_BATCH_EVERY": "5"})
    assert (s.slam.enabled, s.slam.batch_every) == (True, 5)
    with pytest.raises(BadInput, match="HYBRIDLOC_SLAM_ENABLED"):
        load_settings(None, {"HYBRIDLOC_SLAM_ENABLED": "maybe"})


def test_ingest_workers_a_count_or_auto(tmp_path):
    """``ingest_workers``: "auto" by default (serve resolves it), or a whole number, from the file or the environment."""
    assert load_settings(None, {}).ingest_workers == "auto"
    f = tmp_path / "w.toml"
    f.write_text("ingest_workers = 0\n")
    assert load_settings(f, {}).ingest_workers == 0
    assert load_settings(f, {"HYBRIDLOC_INGEST_WORKERS": "3"}).ingest_workers == 3
    assert load_settings(f, {"HYBRIDLOC_INGEST_WORKERS": "auto"}).ingest_workers == "auto"
    with pytest.raises(BadInput, match="HYBRIDLOC_INGEST_WORKERS"):
        load_settings(None, {"HYBRIDLOC_INGEST_WORKERS": "-2"})


def test_bad_environment_names_the_variable():
    with pytest.raises(BadInput, match="HYBRIDLOC_ENDPIONT"):
        load_settings(None, {"HYBRIDLOC_ENDPIONT": "tcp/1.2.3.4:7447"})
    with pytest.raises(BadInput, match="HYBRIDLOC_FILTER_SPEED"):
        load_settings(None, {"HYBRIDLOC_FILTER_SPEED": "fast"})


def test_unreadable_files(tmp_path):
    with pytest.raises(MissingData, match="no such"):
        load_settings(tmp_path / "none.toml", {})
    (tmp_path / "empty.toml").write_text("")
    with pytest.raises(MissingData, match="empty"):
        load_settings(tmp_path / "empty.toml", {})
    with pytest.raises(MissingData, match="folder"):
        load_settings(tmp_path, {})
    (tmp_path / "junk.toml").write_text("= = [")
    with pytest.raises(DataFormatError, match="TOML"):
        load_settings(tmp_path / "junk.toml", {})


def test_command_line_precedence_option_env_file(tmp_path, monkeypatch, capsys):
    """db upgrade on real SQLite files: the option beats the environment, which beats the file."""
    from hybridloc.cli import main

    monkeypatch.chdir(tmp_path)
    for var in ("HYBRIDLOC_DB", "HYBRIDLOC_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    f = tmp_path / "hybridloc.toml"
    f.write_text(FILE)
    assert main(["--config", str(f), "db", "upgrade"]) == 0
    assert (tmp_path / "from-file.db").is_file()
    monkeypatch.setenv("HYBRIDLOC_DB", "from-env.db")
    assert main(["--config", str(f), "db", "upgrade"]) == 0
    assert (tmp_path / "from-env.db").is_file()
    assert main(["--config", str(f), "db", "upgrade", "--db", "from-option.db"]) == 0
    assert (tmp_path / "from-option.db").is_file()
    out = capsys.readouterr().out
    assert "from-file.db: schema at revision" in out and "from-option.db: schema at revision" in out
    # a required option may come from the settings: map export's --site
    monkeypatch.delenv("HYBRIDLOC_DB")
    assert main(["--config", str(f), "map", "export", "--out", "m.npz"]) == 2  # the site comes from the file; no map stored
    assert "no radio map stored for site 'site1'" in capsys.readouterr().err
