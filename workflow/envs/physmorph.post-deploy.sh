#!/usr/bin/env bash
# Snakemake runs this in the new environment of physmorph.yaml (and of physmorph_cuda.yaml, whose
# post-deploy script is a link to this one; --use-conda), from the workflow's working directory,
# once the lock's pins are in: it installs physmorph itself as `make venv` does, editable, so the
# environment follows this checkout's code. The checkout is the folder of the
# Snakefile the working directory holds (a link to it in a scratch working directory).
set -euo pipefail
if [ ! -e Snakefile ]; then
    echo "physmorph.post-deploy.sh: no Snakefile in $(pwd): run snakemake --use-conda from the checkout" >&2
    exit 1
fi
checkout="$(dirname "$(readlink -f Snakefile)")"
python -m pip install --quiet --no-deps --no-build-isolation -e "$checkout"
