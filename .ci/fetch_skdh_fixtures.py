#!/usr/bin/env python3
"""Fetch scikit-digital-health's own .cwa / .bin test fixtures for tests/daemon/test_formats.py.

    python3 .ci/fetch_skdh_fixtures.py DIR

They are the reader's own test files (tests/io/data of its source distribution on PyPI), not ours
to commit: this downloads that sdist (the installed version's, else the newest), checks its sha256
against PyPI's and extracts only the fixture files into DIR, outside the repository. Prints DIR.
"""
from __future__ import annotations

import hashlib
import io
import json
import sys
import tarfile
import urllib.parse
import urllib.request
from importlib import metadata
from pathlib import Path

PROJECT = "scikit-digital-health"
WANTED = ("ax3_sample.cwa", "gnactv_sample.bin")


def sdist_url(version: str | None) -> tuple[str, str]:
    api = f"https://pypi.org/pypi/{PROJECT}/json"
    with urllib.request.urlopen(api, timeout=30) as r:
        info = json.load(r)
    files = info["releases"].get(version, []) if version else info["urls"]
    for f in files:
        if f["packagetype"] == "sdist":
            return urllib.parse.urljoin(api, f["url"]), f["digests"]["sha256"]
    raise SystemExit(f"no source distribution of {PROJECT} {version or ''} on PyPI")


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    out = Path(argv[0]).expanduser()
    if all((out / name).is_file() for name in WANTED):
        print(out)
        return 0
    try:
        version: str | None = metadata.version(PROJECT)
    except metadata.PackageNotFoundError:
        version = None
    url, sha256 = sdist_url(version)
    with urllib.request.urlopen(url, timeout=120) as r:
        blob = r.read()
    if hashlib.sha256(blob).hexdigest() != sha256:
        raise SystemExit(f"{url}: sha256 does not match PyPI's")
    out.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(blob), mode="r:gz") as tar:
        for member in tar.getmembers():
            name = member.name.rsplit("/", 1)[-1]
            if member.isfile() and "/tests/io/data/" in member.name and name in WANTED:
                (out / name).write_bytes(tar.extractfile(member).read())
    missing = [n for n in WANTED if not (out / n).is_file()]
    if missing:
        raise SystemExit(f"{url}: fixtures not found in the sdist: {', '.join(missing)}")
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
