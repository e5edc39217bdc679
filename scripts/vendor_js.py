"""Vendor the dashboard's JavaScript libraries into the package (no build step, no CDN at run time).

Each library is fetched from the npm registry with ``npm pack NAME@VERSION`` (the registry's own
tarball, checked against the pinned Subresource-Integrity hash below), and only the files the page
loads are copied, with the library's LICENSE, to ``server/dashboard/static/vendor/<name>/``.
``MANIFEST.json`` there records name, version, integrity and the sha256 of every copied file;
``tests/test_dashboard_http.py`` checks the files against it without network.

Run again after changing a pin: ``python scripts/vendor_js.py``.
"""

from __future__ import annotations

import base64
import hashlib
import json
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VENDOR = ROOT / "server" / "dashboard" / "static" / "vendor"

#: name -> (version, npm dist.integrity, {file in the tarball: file in the vendor folder})
PINS = {
    "leaflet": (
        "1.9.4",
        "sha512-nxS1ynzJOmOlHp+iL3FyWqK89GtNL8U8rvlMOsQdTTssxZwCXh8N2NB3GDQOL+YR3XnWyZAxwQixURb+FA74PA==",
        {
            "package/dist/leaflet.js": "leaflet.js",
            "package/dist/leaflet.css": "leaflet.css",
            "package/dist/images/layers.png": "images/layers.png",
            "package/dist/images/layers-2x.png": "images/layers-2x.png",
            "package/dist/images/marker-icon.png": "images/marker-icon.png",
            "package/dist/images/marker-icon-2x.png": "images/marker-icon-2x.png",
            "package/dist/images/marker-shadow.png": "images/marker-shadow.png",
            "package/LICENSE": "LICENSE",
            "package/package.json": "package.json",
        },
    ),
}


def _integrity(data: bytes) -> str:
    return "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()


def vendor(name: str, version: str, integrity: str, files: dict[str, str]) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(["npm", "pack", f"{name}@{version}", "--silent"], cwd=tmp, capture_output=True, text=True, check=True)
        tgz = Path(tmp) / out.stdout.strip().splitlines()[-1]
        data = tgz.read_bytes()
        if _integrity(data) != integrity:
            raise SystemExit(f"{name}@{version}: the registry's tarball does not match the pinned integrity {integrity}")
        dest = VENDOR / name
        if dest.exists():
            shutil.rmtree(dest)
        with tarfile.open(tgz) as tar:
            for src, rel in files.items():
                member = tar.extractfile(src)
                if member is None:
                    raise SystemExit(f"{name}@{version}: {src} is not in the tarball")
                target = dest / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(member.read())
    return {
        "version": version,
        "integrity": integrity,
        "files": {rel: hashlib.sha256((dest / rel).read_bytes()).hexdigest() for rel in sorted(files.values())},
    }


def main() -> int:
    if shutil.which("npm") is None:
        print("npm is needed to fetch the vendored libraries from the npm registry", file=sys.stderr)
        return 2
    manifest = {name: vendor(name, *pin) for name, pin in PINS.items()}
    (VENDOR / "MANIFEST.json").write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    for name, m in manifest.items():
        print(f"{name}@{m['version']}: {len(m['files'])} files -> {VENDOR / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
