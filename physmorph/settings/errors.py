"""The error of a refused configuration, with the key it refuses as data.

It lives apart from physmorph.settings.workflow so that what the config builds on (the tradeoff study's
points, physmorph.settings.study_points) can refuse a value without importing the settings themselves.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """Invalid configuration. ``key``: the dotted config key refused (None when the error names
    none, e.g. a config file that cannot be read); ``reason``: why, in words, without the key. The
    message says both; code reads the attributes. A ConfigError raised from another one
    (``raise ConfigError(...) from exc``) without a key of its own names that one's key and reason."""

    def __init__(self, message: str, key: str | None = None, reason: str | None = None):
        super().__init__(message)
        self._key = key
        self._reason = reason

    @classmethod
    def for_key(cls, key: str, reason) -> "ConfigError":
        """The refusal of ``key``: its message is ``config key '{key}': {reason}``."""
        return cls(f"config key '{key}': {reason}", key=key, reason=str(reason))

    def _from_cause(self) -> "ConfigError | None":
        return self.__cause__ if self._key is None and isinstance(self.__cause__, ConfigError) else None

    @property
    def key(self) -> str | None:
        cause = self._from_cause()
        return cause.key if cause is not None else self._key

    @property
    def reason(self) -> str:
        cause = self._from_cause()
        if cause is not None:
            return cause.reason
        return self._reason if self._reason is not None else str(self)
