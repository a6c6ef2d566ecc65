"""The key of a morph run: its settings and the content checksums of its inputs. A checkpoint
resumes only under an equal key; otherwise the run restarts and says what changed."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass


@dataclass(frozen=True)
class RunKey:
    """What a checkpoint may be resumed with: the run's settings and the content of its inputs."""

    settings: str  # the run's settings as sorted JSON
    inputs: tuple[tuple[str, str], ...]  # (role, content checksum), e.g. ("target", "3f1c...")

    @property
    def digest(self) -> str:
        blob = json.dumps({"settings": self.settings, "inputs": [list(p) for p in self.inputs]}, sort_keys=True)
        return hashlib.sha256(blob.encode("utf-8")).hexdigest()

    def attrs(self) -> dict[str, str]:
        return {"run_key": self.digest, "config_record": self.settings,
                "input_checksums": json.dumps(dict(self.inputs), sort_keys=True)}

    @classmethod
    def from_attrs(cls, attrs) -> "RunKey":
        inputs = json.loads(str(attrs["input_checksums"]))
        return cls(str(attrs["config_record"]), tuple(sorted(inputs.items())))

    def changes_from(self, old: "RunKey") -> list[str]:
        """Why a run with key ``old`` cannot be resumed as this one (empty when it can)."""
        out = []
        new_in, old_in = dict(self.inputs), dict(old.inputs)
        for role in sorted(set(new_in) | set(old_in)):
            if new_in.get(role) != old_in.get(role):
                out.append(f"input '{role}' changed (content checksum {str(old_in.get(role))[:12]} -> "
                           f"{str(new_in.get(role))[:12]})")
        if self.settings != old.settings:
            try:
                a, b = json.loads(old.settings), json.loads(self.settings)
                keys = sorted(_changed_keys(a, b))
            except ValueError:
                keys = []
            out.append("settings changed" + (f" ({', '.join(keys[:6])})" if keys else ""))
        return out


def _changed_keys(a, b, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in set(a) | set(b):
            out += _changed_keys(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [] if a == b else [prefix.rstrip(".")]
