#!/usr/bin/env bash
# The image's base made from Debian packages, for a site that cannot pull python:3.11-slim
# (no Docker Hub): Debian 12 (bookworm) minbase with Python 3.11 in a venv at /usr/local, so
# that `python` and `pip` are where python:3.11-slim has them, imported into the local engine.
#
#   deploy/docker/base-image.sh [NAME]      # default aesop-base:bookworm; needs root,
#                                           # debootstrap and a Debian mirror (AESOP_DEBIAN_MIRROR)
# The Dockerfile then builds FROM it: docker compose build --build-arg BASE_IMAGE=NAME, or
# `make image`, which does both.
set -euo pipefail
name=${1:-aesop-base:bookworm}
mirror=${AESOP_DEBIAN_MIRROR:-http://deb.debian.org/debian}
command -v debootstrap >/dev/null || { echo "base-image.sh: debootstrap is missing (apt-get install debootstrap)" >&2; exit 2; }
[ "$(id -u)" = 0 ] || { echo "base-image.sh: debootstrap needs root" >&2; exit 2; }
rootfs=$(mktemp -d /tmp/aesop-base.XXXXXX)
trap 'rm -rf "$rootfs"' EXIT
debootstrap --variant=minbase --include=ca-certificates bookworm "$rootfs" "$mirror"
# Python by apt inside, not debootstrap's --include: its resolver leaves python3.11-venv's
# dependencies out (python3.11-distutils) and the configure step fails
chroot "$rootfs" apt-get update -q
chroot "$rootfs" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
    --no-install-recommends python3.11 python3.11-venv
chroot "$rootfs" python3.11 -m venv /usr/local
chroot "$rootfs" /usr/local/bin/python -c "import ensurepip, venv, ssl, sqlite3"
chroot "$rootfs" apt-get clean
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs"/tmp/*
tar --numeric-owner -C "$rootfs" -c . | docker import \
    --change 'ENV LANG=C.UTF-8' --change 'CMD ["python"]' - "$name"
echo "base-image.sh: imported $name"
