#!/usr/bin/env bash
# The image's base made from Debian packages, for a site that cannot pull python:3.11-slim
# (no Docker Hub): Debian 12 (bookworm) minbase with Python 3.11 in a venv at /usr/local, so
# that `python` and `pip` are where python:3.11-slim has them, imported into the local engine.
#
#   deploy/docker/base-image.sh [NAME] [--postgres PGNAME]
#       NAME: default aesop-base:bookworm. Needs root, debootstrap and a Debian mirror
#       (AESOP_DEBIAN_MIRROR). --postgres: also PostgreSQL 15 for compose.fleet's replicas
#       (AESOP_POSTGRES_IMAGE=PGNAME), the same base and Debian's postgresql-15, run as uid
#       10001 by postgres-entrypoint.sh, for a site that cannot pull postgres:15
#   deploy/docker/base-image.sh --check [NAME] [--postgres PGNAME]
#       exits 0 when the images are there and NAME holds this script's packages (its label
#       org.aesop.base.packages), 1 when they must be made (again); no root needed
# The Dockerfile then builds FROM it: docker compose build --build-arg BASE_IMAGE=NAME, or
# `make image`, which does both.
set -euo pipefail
name=aesop-base:bookworm
postgres=
check=
# Python 3.11 and the run-time libraries the images' wheels load from the system: libgomp1
# (OpenMP) for llama-cpp-python's, which `make llama` builds on the host (smollm2.Dockerfile).
# A base made with another list is made again by `make image` (--check).
packages="python3.11 python3.11-venv libgomp1"
label="org.aesop.base.packages=\"$packages\""
while [ $# -gt 0 ]; do
    case $1 in
        --postgres) postgres=${2:?--postgres NAME}; shift 2 ;;
        --check) check=1; shift ;;
        -*) echo "base-image.sh: unknown option $1" >&2; exit 2 ;;
        *) name=$1; shift ;;
    esac
done
if [ -n "$check" ]; then
    held=$(docker image inspect -f '{{index .Config.Labels "org.aesop.base.packages"}}' \
        "$name" 2>/dev/null) || exit 1
    [ "$held" = "$packages" ] || {
        echo "base-image.sh: $name was not made with $packages: make it again" >&2; exit 1; }
    [ -z "$postgres" ] || docker image inspect "$postgres" >/dev/null 2>&1 || exit 1
    exit 0
fi
here=$(cd "$(dirname "$0")" && pwd)
mirror=${AESOP_DEBIAN_MIRROR:-http://deb.debian.org/debian}
command -v debootstrap >/dev/null || { echo "base-image.sh: debootstrap is missing (apt-get install debootstrap)" >&2; exit 2; }
[ "$(id -u)" = 0 ] || { echo "base-image.sh: debootstrap needs root" >&2; exit 2; }
rootfs=$(mktemp -d /tmp/aesop-base.XXXXXX)
trap 'rm -rf "$rootfs"' EXIT
debootstrap --variant=minbase --include=ca-certificates bookworm "$rootfs" "$mirror"
# Python by apt inside, not debootstrap's --include: its resolver leaves python3.11-venv's
# dependencies out (python3.11-distutils) and the configure step fails
chroot "$rootfs" apt-get update -q
# shellcheck disable=SC2086  # the list, one package a word
chroot "$rootfs" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
    --no-install-recommends $packages
chroot "$rootfs" python3.11 -m venv /usr/local
chroot "$rootfs" /usr/local/bin/python -c "import ensurepip, venv, ssl, sqlite3"
chroot "$rootfs" apt-get clean
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs"/tmp/*
tar --numeric-owner -C "$rootfs" -c . | docker import --change "LABEL $label" \
    --change 'ENV LANG=C.UTF-8' --change 'CMD ["python"]' - "$name"
echo "base-image.sh: imported $name"
[ -n "$postgres" ] || exit 0

# PostgreSQL: Debian's server, no cluster of its own (the entrypoint makes one in the volume)
printf '#!/bin/sh\nexit 101\n' > "$rootfs/usr/sbin/policy-rc.d"  # no service starts here
chmod +x "$rootfs/usr/sbin/policy-rc.d"
chroot "$rootfs" apt-get update -q
chroot "$rootfs" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
    --no-install-recommends postgresql-common
sed -i 's/^#* *create_main_cluster.*/create_main_cluster = false/' \
    "$rootfs/etc/postgresql-common/createcluster.conf"
chroot "$rootfs" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
    --no-install-recommends postgresql-15
chroot "$rootfs" useradd --system --uid 10001 --user-group --no-create-home \
    --home-dir /var/lib/postgresql --shell /usr/sbin/nologin aesop
mkdir -p "$rootfs/var/lib/postgresql/data"
chroot "$rootfs" chown -R aesop:aesop /var/lib/postgresql
chmod 0700 "$rootfs/var/lib/postgresql/data"
install -m 0755 "$here/postgres-entrypoint.sh" "$rootfs/usr/local/bin/postgres-entrypoint"
chroot "$rootfs" apt-get clean
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs/usr/sbin/policy-rc.d"
tar --numeric-owner -C "$rootfs" -c . | docker import \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PATH=/usr/lib/postgresql/15/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV PGDATA=/var/lib/postgresql/data' \
    --change 'USER 10001' --change 'EXPOSE 5432' \
    --change 'ENTRYPOINT ["/usr/local/bin/postgres-entrypoint"]' - "$postgres"
echo "base-image.sh: imported $postgres"
