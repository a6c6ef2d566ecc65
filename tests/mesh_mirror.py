"""Where the tests find the raw benchmark meshes, and their download when no mirror holds them
(tests/conftest.py's mesh_dir fixture; tests/meshes/test_mesh_fixture.py tests the download's
failures). A module of its own so that every test folder imports it by one name."""

from __future__ import annotations

import errno
import http.client
import os
import socket
import urllib.error
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# Published SHA-256 of the raw benchmark meshes (as pinned in config/config.yaml raw_meshes).
RAW_MESH_SHA256 = {
    "stanford-bunny.obj": "1eb35d1e21ce99e5ce911353b6be278990713448dd9e8f5c9387f9de39b32205",
    "spot.obj": "0738b5e8608fed74e5e8c7aa8dd0af97b4b74f9f6cbf7aac84cd7e40b2e44a75",
    "cow.obj": "69afce548640bc2beb0c44894d1a24d5766cc9cd3fd74f3ec55b4e229104b23f",
    "Duck.glb": "49e23fa9faead02dd9b8ae45bc63b945bce068c1361dc00485596f4ba723b27d",
}


def mesh_dir_candidates() -> list[Path]:
    env = os.environ.get("PHYSMORPH_MESH_DIR")
    return ([Path(env)] if env else []) + [REPO_ROOT.parent / "shared" / "meshes", REPO_ROOT / "resources" / "meshes"]


def find_mesh_dir() -> Path | None:
    for candidate in mesh_dir_candidates():
        if all((candidate / name).is_file() for name in RAW_MESH_SHA256):
            return candidate
    return None


def fetch_raw_meshes(dest: Path, sources: dict | None = None) -> Path:
    """Download the four raw meshes into ``dest`` (sources: file name -> physmorph.settings.workflow.RawMesh,
    default config/config.yaml's raw_meshes), each checked against its published SHA-256."""
    from physmorph.settings.workflow import load_settings
    from physmorph.meshes.fetch import fetch_mesh

    if sources is None:
        sources = load_settings(REPO_ROOT / "config" / "config.yaml").raw_meshes
    for name, sha256 in RAW_MESH_SHA256.items():
        fetch_mesh(name, sources[name].url, sha256, dest)
    return dest


# errno values of an OSError that say the network is missing or refused the connection
NETWORK_ERRNOS = frozenset({errno.ENETUNREACH, errno.ENETDOWN, errno.ENETRESET, errno.EHOSTUNREACH, errno.EHOSTDOWN,
                            errno.ECONNREFUSED, errno.ECONNRESET, errno.ECONNABORTED, errno.ETIMEDOUT,
                            errno.EADDRNOTAVAIL})
# errors of the local file system: urllib wraps them in a URLError for a file:// URL
_LOCAL_ERRORS = (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError)


def is_network_failure(exc: BaseException) -> bool:
    """Whether ``exc`` says the network failed: the exception or one it was raised from (``raise ...
    from``, as physmorph.meshes.fetch.fetch_mesh wraps a failed download in its FetchError) is a URLError
    (an HTTP error included: a proxy's refusal, a moved URL) that is not a local file error, a socket
    or DNS error, a timeout, a dropped connection (ConnectionError, http.client's errors) or an
    OSError with a network errno. A checksum mismatch (a FetchError raised from nothing), a
    disk error and an error in the project's code are not."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, urllib.error.URLError):
            return not isinstance(getattr(exc, "reason", None), _LOCAL_ERRORS)
        if isinstance(exc, (socket.gaierror, socket.herror, TimeoutError, ConnectionError, http.client.HTTPException)):
            return True
        if isinstance(exc, OSError) and exc.errno in NETWORK_ERRNOS:
            return True
        exc = exc.__cause__  # only an explicit wrap: not an error raised while handling another
    return False


def fetch_or_skip(dest: Path, sources: dict | None = None) -> Path:
    """fetch_raw_meshes(dest, sources), skipping the calling test (pytest.skip) when the download
    failed for want of a network (is_network_failure) and raising anything else: a checksum
    mismatch or a bug must fail the tests, not skip them."""
    try:
        return fetch_raw_meshes(dest, sources)
    except Exception as exc:
        if not is_network_failure(exc):
            raise
        looked = ", ".join(str(p) for p in mesh_dir_candidates())
        pytest.skip(f"raw benchmark meshes not found (looked in {looked}) and the download failed for want of a "
                    f"network ({exc}); set PHYSMORPH_MESH_DIR to a directory holding them")
