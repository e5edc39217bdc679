"""The import contract (issue #19), checked on every module's syntax tree, imports inside functions
included:

1. the library (``hybridloc/`` but for the command line ``hybridloc/cli/`` and the two harnesses that run a
   server and its clients, ``hybridloc/demo.py`` and ``hybridloc/crowd_eval.py``)
   never imports ``hybridloc.server``, ``hybridloc.clients``, ``hybridloc.cli`` or ``hybridloc.demo``:
   the applications stand on the library, never the reverse;
2. ``server/`` (installed as ``hybridloc.server``) and ``clients/`` (``hybridloc.clients``) never import
   each other, nor the command line or the demo.

Relative imports are resolved against the installed names (package-dir of pyproject.toml).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# folder -> installed package name (pyproject.toml's package-dir)
PACKAGES = {"hybridloc": ROOT / "hybridloc", "hybridloc.server": ROOT / "server", "hybridloc.clients": ROOT / "clients"}
APPLICATIONS = ("hybridloc.server", "hybridloc.clients", "hybridloc.cli", "hybridloc.demo")


def module_name(py: Path) -> tuple[str, bool]:
    """(dotted name, is a package __init__) of a source file."""
    for pkg, folder in sorted(PACKAGES.items(), key=lambda kv: -len(str(kv[1]))):
        if py.is_relative_to(folder):
            parts = list(py.relative_to(folder).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            return ".".join([pkg, *parts]), is_pkg
    raise ValueError(py)


def imported_modules(py: Path) -> set[str]:
    """Every module ``py`` imports (absolute, relative resolved; ``from X import y`` counts X and X.y)."""
    name, is_pkg = module_name(py)
    package = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(py.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def _sources(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.py") if ".venv" not in p.parts)


def _library_sources() -> list[Path]:
    lib = PACKAGES["hybridloc"]
    return [p for p in _sources(lib) if not p.is_relative_to(lib / "cli") and p not in (lib / "demo.py", lib / "crowd_eval.py")]


def _hits(py: Path, forbidden: tuple[str, ...]) -> list[str]:
    return sorted(m for m in imported_modules(py) if any(m == f or m.startswith(f + ".") for f in forbidden))


@pytest.mark.parametrize("py", _library_sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_library_never_imports_the_applications(py):
    assert not _hits(py, APPLICATIONS), f"{py.relative_to(ROOT)} imports an application: {_hits(py, APPLICATIONS)}"


def test_server_and_clients_never_import_each_other_nor_the_command_line():
    for side, other in (("hybridloc.server", "hybridloc.clients"), ("hybridloc.clients", "hybridloc.server")):
        for py in _sources(PACKAGES[side]):
            bad = _hits(py, (other, "hybridloc.cli", "hybridloc.demo"))
            assert not bad, f"{py.relative_to(ROOT)} imports {bad}"


def test_the_checker_sees_relative_and_lazy_imports(tmp_path, monkeypatch):
    """A library module importing the server lazily, by a relative import, is caught."""
    fake = tmp_path / "hybridloc" / "radio"
    fake.mkdir(parents=True)
    (fake / "leak.py").write_text("def f():\n    from ..server.store import Store\n    from . import locate\n")
    monkeypatch.setitem(PACKAGES, "hybridloc", tmp_path / "hybridloc")
    mods = imported_modules(fake / "leak.py")
    assert "hybridloc.server.store" in mods and "hybridloc.radio.locate" in mods
    assert _hits(fake / "leak.py", APPLICATIONS) == ["hybridloc.server.store", "hybridloc.server.store.Store"]
