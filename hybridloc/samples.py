"""Paths of the real data samples bundled with the package (see each folder's README)."""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent / "data"
#: Indoor Location Competition 2.0, site1 floor F1: 35 walks + floor plan (MIT licence); clients.txt names the demo's clients.
ILC_SITE1_F1 = DATA_DIR / "ilc_site1_F1"
