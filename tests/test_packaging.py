"""The layout is the architecture: check it stays so."""

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(folder: Path) -> set[str]:
    mods = set()
    for py in folder.rglob("*.py"):
        tree = ast.parse(py.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                mods.add(node.module)
    return mods


def test_every_package_folder_is_listed_in_pyproject():
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(conf["packages"])
    mapping = conf["package-dir"]
    found = set()
    for dotted, folder in mapping.items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            name = ".".join([dotted, *rel.parts]) if rel.parts else dotted
            if name.startswith("hybridloc.server") and dotted == "hybridloc":
                continue
            found.add(name)
    assert found <= listed, f"packages missing from pyproject.toml: {sorted(found - listed)}"


def test_server_and_clients_never_import_each_other():
    assert not any(m.startswith("hybridloc.clients") for m in _imports(ROOT / "server"))
    assert not any(m.startswith("hybridloc.server") for m in _imports(ROOT / "clients"))


def test_library_does_not_touch_network_or_database():
    """hybridloc/ may only use Zenoh in its wire-contract module, and never SQL."""
    for py in (ROOT / "hybridloc").rglob("*.py"):
        mods: set[str] = set()
        tree = ast.parse(py.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                mods.add(node.module)
        assert not any(m.split(".")[0] in ("sqlalchemy", "alembic", "psycopg") for m in mods), py
        if py.parent.name != "wire":
            assert "zenoh" not in {m.split(".")[0] for m in mods}, f"{py} imports zenoh outside hybridloc/wire"


def test_conventions_written_once():
    import hybridloc

    doc = hybridloc.__doc__
    for phrase in ("SI", "radians", "float seconds", "East-North-Up", "quat_wxyz", "R_body_to_nav", "geodetic origin"):
        assert phrase in doc
