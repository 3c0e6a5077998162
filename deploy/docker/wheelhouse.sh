#!/usr/bin/env bash
# The image's Python packages for a build with no index (no Docker Hub, no PyPI, no PyTorch
# index inside the build): the locked set, deploy/docker/requirements.lock (pyproject.toml's
# dependencies resolved, torch's CPU build included), downloaded as wheels into
# .cache/wheelhouse on the host, which reaches an index (or a mirror of one: pip's own
# config applies). The Dockerfile installs from there with `pip install --no-index`.
#
#   deploy/docker/wheelhouse.sh          # fetch what the lock names (what is there is kept)
#   deploy/docker/wheelhouse.sh --lock   # resolve pyproject.toml again, rewrite the lock
# PYTHON: a Python 3.11 on Linux x86_64 with pip (the image's), default python3.
set -euo pipefail
cd "$(dirname "$0")/../.."
python=${PYTHON:-python3}
lock=deploy/docker/requirements.lock
out=.cache/wheelhouse
if [ "${1:-}" = --lock ]; then
    report=$(mktemp)
    trap 'rm -f "$report"' EXIT
    "$python" -m pip install --dry-run --ignore-installed --quiet --report "$report" \
        torch==2.13.0 wheel .
    "$python" - "$report" > "$lock.new" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
pins = sorted((i["metadata"]["name"], i["metadata"]["version"]) for i in report["install"]
              if i["metadata"]["name"] != "aesop-stack")
print("# The image's Python packages: pyproject.toml's dependencies resolved for Python 3.11")
print("# on Linux x86_64, torch's CPU build. Written by deploy/docker/wheelhouse.sh --lock.")
for name, version in sorted(pins, key=lambda p: p[0].lower()):
    print(f"{name}=={version}")
PY
    mv "$lock.new" "$lock"
    echo "wheelhouse.sh: wrote $lock"
fi
mkdir -p "$out"
"$python" -m pip download --quiet --no-deps --only-binary=:all: --dest "$out" -r "$lock"
echo "wheelhouse.sh: $out holds $(ls "$out" | wc -l) wheels ($(du -sh "$out" | cut -f1))"
