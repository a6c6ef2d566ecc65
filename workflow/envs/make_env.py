"""Write the conda environments the rules name (`conda:`) from the locks: workflow/envs/physmorph.yaml
from environment.lock (torch's CPU build, from PyTorch's CPU wheel index) and physmorph_cuda.yaml
from environment.cuda.lock (torch's CUDA build, from PyPI), each the lock's Python version and,
through pip, its exact pins, as `make venv` / `make venv DEVICE=cuda` install them. The rules take
the CUDA one when the config says `device: cuda`. physmorph itself is installed into it by
physmorph.post-deploy.sh. Snakemake uses them only with `--use-conda`.

    python workflow/envs/make_env.py          # (make conda-env) rewrite them after a lock changed
    python workflow/envs/make_env.py --check  # exit 1 when one is out of date
"""

import argparse
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LOCK = REPO / "environment.lock"
ENV_FILE = Path(__file__).resolve().with_name("physmorph.yaml")
CUDA_LOCK = REPO / "environment.cuda.lock"
CUDA_ENV_FILE = Path(__file__).resolve().with_name("physmorph_cuda.yaml")
# the Makefile's TORCH_CPU_INDEX: torch's CPU build (2.13.0+cpu) is not on PyPI
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def lock_python(lock_text: str) -> str:
    """The Python version the lock was made for, from its header ("... (Python 3.11, pip) ...")."""
    match = re.search(r"^#.*\bPython (\d+\.\d+)\b", lock_text, re.M)
    if match is None:
        raise ValueError("environment.lock: no 'Python X.Y' in its header comment")
    return match[1]


def lock_pins(lock_text: str) -> list[str]:
    """The lock's requirement lines (name==version), in its order, without comments."""
    lines = (line.split("#", 1)[0].strip() for line in lock_text.splitlines())
    return [line for line in lines if line]


def conda_env_text(lock_text: str, lock_name: str = "environment.lock",
                   index: str | None = TORCH_CPU_INDEX, when: str = "") -> str:
    """The environment file's text for the lock ``lock_text`` (named ``lock_name``); ``index``: an
    extra pip index (torch's CPU wheels; None for the CUDA lock, whose torch is on PyPI); ``when``:
    the config that selects it."""
    pins = "".join(f"      - {pin}\n" for pin in lock_pins(lock_text))
    return (
        f"# Generated from {lock_name} by workflow/envs/make_env.py (make conda-env): do not edit.\n"
        f"# The environment of every rule under `snakemake --use-conda`{when}; physmorph itself is installed\n"
        "# from this checkout by physmorph.post-deploy.sh.\n"
        "channels:\n"
        "  - conda-forge\n"
        "  - nodefaults\n"
        "dependencies:\n"
        f"  - python={lock_python(lock_text)}\n"
        "  - pip\n"
        "  - pip:\n"
        + (f"      - --extra-index-url {index}\n" if index else "")
        + pins
    )


def env_texts() -> dict[Path, str]:
    """Each environment file and the text its lock gives."""
    return {ENV_FILE: conda_env_text(LOCK.read_text()),
            CUDA_ENV_FILE: conda_env_text(CUDA_LOCK.read_text(), CUDA_LOCK.name, index=None,
                                           when=" with `device: cuda`")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only check that the files match the locks")
    args = parser.parse_args(argv)
    stale = []
    for path, text in env_texts().items():
        if args.check:
            if not path.is_file() or path.read_text() != text:
                stale.append(path)
            continue
        path.write_text(text)
        print(f"wrote {path.relative_to(REPO)}")
    for path in stale:
        print(f"{path.relative_to(REPO)} is out of date with its lock: run `make conda-env`", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
