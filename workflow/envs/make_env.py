"""Write workflow/envs/physmorph.yaml, the conda environment every rule names (`conda:`), from
environment.lock: the lock's Python version and, through pip, its exact pins, as `make venv`
installs them (torch's CPU build from PyTorch's CPU wheel index). physmorph itself is installed
into it by physmorph.post-deploy.sh. Snakemake uses it only with `--use-conda`.

    python workflow/envs/make_env.py          # (make conda-env) rewrite it after the lock changed
    python workflow/envs/make_env.py --check  # exit 1 when it is out of date
"""

import argparse
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LOCK = REPO / "environment.lock"
ENV_FILE = Path(__file__).resolve().with_name("physmorph.yaml")
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


def conda_env_text(lock_text: str) -> str:
    """The environment file's text for the lock ``lock_text``."""
    pins = "".join(f"      - {pin}\n" for pin in lock_pins(lock_text))
    return (
        "# Generated from environment.lock by workflow/envs/make_env.py (make conda-env): do not edit.\n"
        "# The environment of every rule under `snakemake --use-conda`; physmorph itself is installed\n"
        "# from this checkout by physmorph.post-deploy.sh.\n"
        "channels:\n"
        "  - conda-forge\n"
        "  - nodefaults\n"
        "dependencies:\n"
        f"  - python={lock_python(lock_text)}\n"
        "  - pip\n"
        "  - pip:\n"
        f"      - --extra-index-url {TORCH_CPU_INDEX}\n"
        f"{pins}"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only check that the file matches the lock")
    args = parser.parse_args(argv)
    text = conda_env_text(LOCK.read_text())
    if args.check:
        if not ENV_FILE.is_file() or ENV_FILE.read_text() != text:
            print(f"{ENV_FILE.relative_to(REPO)} is out of date with environment.lock: run `make conda-env`",
                  file=sys.stderr)
            return 1
        return 0
    ENV_FILE.write_text(text)
    print(f"wrote {ENV_FILE.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
