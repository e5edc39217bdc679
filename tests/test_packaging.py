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


# server/ and clients/ never importing each other: tests/test_architecture.py (with the rest of the import contract)


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


# import name -> distribution name, where they differ
# module -> the core dependency that installs it (distributed comes with dask[distributed])
_DIST_OF = {"sklearn": "scikit-learn", "zenoh": "eclipse-zenoh", "distributed": "dask"}


def test_plain_install_brings_every_package_imported():
    """A plain ``pip install .`` (no extras) must run every command: each third-party package that
    hybridloc/, server/, clients/ or migrations/ imports is a core dependency. Optional ones (psycopg,
    the postgres extra) are reached only through hybridloc.errors.require, which names the extra."""
    import re
    import sys

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {re.split(r"[<>=!\[ ;]", d, maxsplit=1)[0].lower() for d in project["dependencies"]}
    used: set[str] = set()
    for folder in ("hybridloc", "server", "clients", "migrations"):
        for py in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(py.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    used.update(a.name.split(".")[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    used.add(node.module.split(".")[0])
    third_party = {m for m in used if m not in sys.stdlib_module_names and m != "hybridloc"}
    missing = {m for m in third_party if _DIST_OF.get(m, m).lower() not in core}
    assert not missing, f"imported but not core dependencies: {sorted(missing)}"
    assert "plot" in project["optional-dependencies"], "the plot extra stays (pip install '.[test,plot]')"


_REFUSE = """
import sys
class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, Refuse())
from hybridloc.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _without(blocked: set[str], *args: str, cwd: Path):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-c", _REFUSE.format(blocked=blocked), *args], capture_output=True, text=True, timeout=120, cwd=cwd)


def test_missing_optional_package_is_one_line_naming_the_extra(tmp_path):
    """PostgreSQL without psycopg, and the demo without matplotlib (a trimmed install): one line that
    says which extra to install, exit status 2, no traceback; nothing is connected or computed first."""
    r = _without({"psycopg"}, "db", "upgrade", "--db", "postgresql+psycopg://nobody@127.0.0.1:9/none", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "hybridloc[postgres]" in r.stderr and "Traceback" not in r.stderr
    r = _without({"matplotlib"}, "demo", "--out", str(tmp_path / "demo"), cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "hybridloc[plot]" in r.stderr and "Traceback" not in r.stderr
