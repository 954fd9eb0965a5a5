#!/usr/bin/env bash
# Download into ./.whl the wheels a GPU machine with Python 3.12 and torch (but not the rest of bpp's packages) needs
# to run the bench/gpu_*.sh scripts, at the exact versions of requirements.lock (the newest zarr, for one, needs
# msgspec, which the lock's does not; the lock's needs numcodecs). Run from the repository's root; install there with
#   python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD/src
set -euo pipefail
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
mkdir -p .whl
names="diffusers gymnasium zarr numcodecs hershey-fonts svgpathtools tyro farama-notifications svgwrite
  docstring-parser typeguard donfig google-crc32c importlib-metadata lazy-importer"
for name in $names; do
  pin=$(grep -i "^${name}==" requirements.lock | cut -d' ' -f1)
  [ -n "$pin" ] || { echo "gpu_wheels.sh: $name is not in requirements.lock" >&2; exit 1; }
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl "$pin"
done
du -sh .whl
