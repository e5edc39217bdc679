"""Digests of what the demo and the eval commands print and write, for the refactor contract
("outputs identical" in issues #18 and #19).

    python scripts/digest_outputs.py OUT_DIR [--only NAME ...] [--hybridloc PATH]

For each command it keeps the printed output with wall times masked (``<t>``) in
``OUT_DIR/<name>.txt``, the sha256 of every file it wrote in ``OUT_DIR/<name>.files``, and prints
one digest line per command plus a final JSON line ``{name: sha256}``. Run it before and after a
change and ``diff -r`` the two folders; databases and spools (server state stamped with wall-clock
receive times) are listed with their size only.
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

SHARED = "../shared/data"
COMMANDS: dict[str, list[str]] = {
    "demo": ["demo", "--out", "{out}"],
    "demo-sim": ["demo", "--sim", "--out", "{out}"],
    "demo-no-slam": ["demo", "--no-slam", "--out", "{out}"],  # the demo as it was before the server's crowd SLAM (issue #21)
    "eval-pdr-phone": ["eval", "pdr-phone", f"{SHARED}/msft-ilc/site1"],
    "eval-pdr-foot": ["eval", "pdr-foot", f"{SHARED}/pyshoe-vicon"],
    "eval-fingerprint": ["eval", "fingerprint"],
    "eval-fusion": ["eval", "fusion", f"{SHARED}/msft-ilc/site1", "--out", "{out}"],
    "eval-sim-realism": ["eval", "sim-realism"],
}
# wall times: "12.3 s", "in 4 s", "causal, 120 s", "(0:01:02)", "850x real time", rates per second
_MASKS = [
    (re.compile(r"\b\d+(\.\d+)?\s?(s|ms|min)\b(?!\w)"), "<t>"),
    (re.compile(r"\b\d+(\.\d+)?x real time"), "<t>x real time"),
    (re.compile(r"\b\d[\d,]*(\.\d+)?\s*(steps|scans|samples)/s\b"), "<rate>"),
    (re.compile(r"(tcp|udp|tls)/([\d.]+|\[[\d:a-f]*\]|localhost):\d+"), r"\1/\2:<port>"),  # free ports differ run to run
]
_STATE_SUFFIXES = (".db", ".sqlite", ".sqlite3", ".spool", ".db-wal", ".db-shm", ".log")


def mask(text: str) -> str:
    lines = []
    for line in text.splitlines():
        if line.startswith("[") and "%" in line and "|" in line:  # progress bars
            continue
        for pat, rep in _MASKS:
            line = pat.sub(rep, line)
        lines.append(line)
    return "\n".join(lines) + "\n"


def file_digest(f: Path) -> str:
    """sha256 of a file's content; of the decompressed content for .gz (gzip stamps its header with
    the wall-clock time)."""
    data = f.read_bytes()
    if f.suffix == ".gz":
        data = gzip.decompress(data)
    return hashlib.sha256(data).hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--hybridloc", default=str(Path(sys.executable).with_name("hybridloc")))
    ap.add_argument("--rescan", action="store_true", help="run nothing: re-mask and re-hash what OUT already holds")
    a = ap.parse_args()
    root = Path(a.out).resolve()
    root.mkdir(parents=True, exist_ok=True)
    digests = {}
    for name, argv in COMMANDS.items():
        if a.only and name not in a.only:
            continue
        out = root / "files" / name
        if a.rescan:
            if not (root / f"{name}.txt").exists():
                continue
            text = mask((root / f"{name}.txt").read_text())
            rc = text.rstrip().rsplit(" ", 1)[-1]
        else:
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir(parents=True)
            cmd = [a.hybridloc] + [x.replace("{out}", str(out)) for x in argv]
            p = subprocess.run(cmd, capture_output=True, text=True)
            text = mask(p.stdout.replace(str(out), "<out>")) + f"exit {p.returncode}\n"
            (root / f"{name}.stderr").write_text(p.stderr)
            rc = str(p.returncode)
        (root / f"{name}.txt").write_text(text)
        rows = []
        for f in sorted(out.rglob("*")):
            if f.is_file():
                rel = f.relative_to(out)
                if f.name.endswith(_STATE_SUFFIXES) or "spool" in rel.parts:
                    rows.append(f"{rel} (state, {f.stat().st_size} bytes)")
                else:
                    rows.append(f"{rel} {file_digest(f)}")
        (root / f"{name}.files").write_text("\n".join(rows) + "\n")
        h = hashlib.sha256((text + "\n".join(r for r in rows if "(state" not in r)).encode()).hexdigest()
        digests[name] = h
        print(f"{name}: {h[:16]} (exit {rc})", flush=True)
    print(json.dumps(digests))
    return 0


if __name__ == "__main__":
    sys.exit(main())
