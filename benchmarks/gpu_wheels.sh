#!/usr/bin/env bash
# The wheels benchmarks/gpu_check.sh installs on a GPU machine with no network (its torch and torch-geometric are
# its own): egcbf's dependencies that such a machine's image lacks, at the versions the CPU environment uses,
# for CPython 3.12 on x86-64 Linux, into DIR (default .whl, ignored by git).
#
#   benchmarks/gpu_wheels.sh [DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DIR=${1:-.whl}
PY=${PYTHON:-.venv/bin/python}
mkdir -p "$DIR"
pkgs=()
for name in roma proxsuite cmeel piqp qpsolvers; do  # the image has numpy, scipy, typer, tqdm, safetensors, ...
  version=$("$PY" -m pip show "$name" 2>/dev/null | sed -n 's/^Version: //p')
  pkgs+=("$name${version:+==$version}")
done
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64; do
  platforms+=(--platform "$p")
done
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
  -d "$DIR" "${pkgs[@]}"
ls -la "$DIR"
