"""A CSV file's column names, as every loader's ``sniff`` reads them before deciding whether the file is its format."""

from __future__ import annotations

import csv
from pathlib import Path


def sniff_csv(path, recognised) -> bool:
    """A source loader's ``sniff``: ``path`` is a ``.csv`` file whose header ``recognised(columns)`` accepts."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        return False
    try:
        return bool(recognised(header_columns(path)))
    except OSError:
        return False


def header_columns(path) -> list[str]:
    """The first line's column names, stripped, quotes removed (RFC 4180: a spreadsheet may quote every field; a
    byte-order mark is skipped)."""
    with open(Path(path), encoding="utf-8-sig", errors="replace", newline="") as fh:
        line = fh.readline()
    return [c.strip() for c in next(csv.reader([line]), [])]
