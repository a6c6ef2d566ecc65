"""The mesh stages' errors."""

class MeshError(ValueError):
    """A mesh cannot be used: the message names the file/shape and why."""


class FetchError(RuntimeError):
    """A raw mesh could not be fetched: unreachable URL, missing mirror file or checksum mismatch."""
