"""The mesh_dir fixture's download (tests/mesh_mirror.py: fetch_or_skip, is_network_failure): only a
missing network skips the ~50 tests that need the raw meshes; a checksum mismatch, a disk error or
a bug in the project's code fails them.

The helper's outcome is caught here, a skip included (pytest.skip raises an exception that is no
Exception, so pytest.raises would let a wrong skip through and the test would show as skipped)."""

from __future__ import annotations

import errno
import http.client
import socket
import urllib.error
from types import SimpleNamespace

import pytest

import physmorph.meshes.fetch
from mesh_mirror import RAW_MESH_SHA256, fetch_or_skip, is_network_failure
from physmorph.meshes.errors import FetchError


def _outcome(call) -> tuple[str, BaseException | None]:
    """("ok", None), ("skip", the skip) or ("raise", the exception) of call()."""
    try:
        call()
    except pytest.skip.Exception as exc:
        return "skip", exc
    except Exception as exc:
        return "raise", exc
    return "ok", None


def _sources(url: str) -> dict:
    return {name: SimpleNamespace(url=url, sha256=sha) for name, sha in RAW_MESH_SHA256.items()}


def _closed_port() -> int:
    """A local TCP port nothing listens on (bound, then closed): a connection to it is refused."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_checksum_mismatch_fails_the_fixture_and_does_not_skip(tmp_path):
    """A download whose bytes do not match the pinned SHA-256 (physmorph.meshes.fetch.fetch_mesh's own
    FetchError, from a file:// URL) is raised, and nothing is left behind."""
    wrong = tmp_path / "wrong.obj"
    wrong.write_text("v 0 0 0\n")
    kind, exc = _outcome(lambda: fetch_or_skip(tmp_path / "meshes", _sources(wrong.as_uri())))
    assert kind == "raise", (kind, exc)
    assert isinstance(exc, FetchError) and "checksum mismatch" in str(exc)
    assert not list((tmp_path / "meshes").iterdir())


def test_a_refused_connection_skips_the_fixture(tmp_path):
    """A download that cannot connect (a local port nothing listens on: fetch_mesh's FetchError
    raised from urllib's URLError) skips, naming where the meshes were looked for."""
    kind, exc = _outcome(lambda: fetch_or_skip(tmp_path / "meshes", _sources(f"http://127.0.0.1:{_closed_port()}/m")))
    assert kind == "skip", (kind, exc)
    assert "for want of a network" in str(exc) and "PHYSMORPH_MESH_DIR" in str(exc)


def test_a_bug_or_a_disk_error_fails_the_fixture(tmp_path, monkeypatch):
    """An error in the project's code (here fetch_mesh raising a TypeError, or a KeyError raised while
    handling a URLError: not raised *from* it) and a local file error (the destination is a file)
    are raised, not skipped."""
    blocked = tmp_path / "file"
    blocked.write_text("")
    kind, exc = _outcome(lambda: fetch_or_skip(blocked, _sources(f"http://127.0.0.1:{_closed_port()}/m")))
    assert kind == "raise" and isinstance(exc, OSError), (kind, exc)

    def buggy(*args, **kwargs):
        raise TypeError("fetch_mesh() got an unexpected keyword argument")

    def bug_while_handling(*args, **kwargs):
        try:
            raise urllib.error.URLError(ConnectionRefusedError(errno.ECONNREFUSED, "refused"))
        except urllib.error.URLError:
            raise KeyError("url")

    for fake, error in ((buggy, TypeError), (bug_while_handling, KeyError)):
        monkeypatch.setattr(physmorph.meshes.fetch, "fetch_mesh", fake)
        kind, exc = _outcome(lambda: fetch_or_skip(tmp_path / "meshes"))
        assert kind == "raise" and isinstance(exc, error), (kind, exc)


def _wrapped(cause: BaseException) -> FetchError:
    try:
        raise FetchError("stanford-bunny.obj: could not download") from cause
    except FetchError as exc:
        return exc


@pytest.mark.parametrize("exc, network", [
    (_wrapped(urllib.error.URLError(socket.gaierror(-3, "Temporary failure in name resolution"))), True),
    (_wrapped(urllib.error.HTTPError("https://x", 403, "Forbidden", None, None)), True),
    (_wrapped(TimeoutError("timed out")), True),
    (_wrapped(ConnectionResetError(errno.ECONNRESET, "reset")), True),
    (_wrapped(OSError(errno.ENETUNREACH, "Network is unreachable")), True),
    (http.client.IncompleteRead(b"partial"), True),
    (FetchError("stanford-bunny.obj: checksum mismatch for https://x"), False),
    (_wrapped(OSError(errno.ENOSPC, "No space left on device")), False),
    (_wrapped(urllib.error.URLError(FileNotFoundError(errno.ENOENT, "no such file"))), False),
    (_wrapped(ValueError("unknown url type: 'htps'")), False),
    (TypeError("a bug"), False),
])
def test_network_failures_are_told_from_other_errors(exc, network):
    assert is_network_failure(exc) is network
