"""Stage 1: fetch one raw mesh (download, or copy from a local mirror) with its SHA-256 verified.

The file is written to ``<dest>.partial`` and renamed only after the checksum matches, so a
failure never leaves a file that looks finished.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import urllib.error
import urllib.request
from pathlib import Path

from .errors import FetchError


def sha256_of(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def fetch_mesh(
    filename: str,
    url: str,
    sha256: str,
    dest_dir: str | os.PathLike,
    mesh_dir: str | os.PathLike | None = None,
    timeout: float = 60.0,
) -> Path:
    """Put the raw mesh ``filename`` into ``dest_dir`` with its SHA-256 verified.

    With ``mesh_dir`` the file is copied from that local mirror; otherwise it is downloaded
    from ``url`` (any scheme urllib understands, file:// included). An existing destination
    with the right checksum is kept as is. Raises FetchError; nothing is left behind on failure.
    """
    if not filename or Path(filename).name != filename:
        raise FetchError(f"mesh filename must be a plain file name, got {filename!r}")
    expected = sha256.strip().lower()
    dest_dir = Path(dest_dir)
    dest = dest_dir / filename
    if dest.exists() and sha256_of(dest) == expected:
        return dest
    dest_dir.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".partial")
    try:
        if mesh_dir is not None:
            src = Path(mesh_dir) / filename
            if not src.is_file():
                raise FetchError(f"{filename}: not found in mesh mirror {Path(mesh_dir)} (looked for {src})")
            shutil.copyfile(src, tmp)
            origin = str(src)
        else:
            origin = url
            try:
                with urllib.request.urlopen(url, timeout=timeout) as response, open(tmp, "wb") as out:
                    shutil.copyfileobj(response, out, length=1 << 20)
            except (urllib.error.URLError, OSError, ValueError) as exc:
                raise FetchError(f"{filename}: could not download {url} ({exc})") from exc
        actual = sha256_of(tmp)
        if actual != expected:
            raise FetchError(
                f"{filename}: checksum mismatch for {origin}: expected sha256 {expected}, got {actual}"
            )
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return dest
