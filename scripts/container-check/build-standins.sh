#!/bin/sh
# Stand-ins for the images the Dockerfile and compose.yaml start from (python:3.11-slim,
# postgres:16), built from Debian's own packages, for a machine whose Docker engine cannot pull
# from Docker Hub but reaches a Debian mirror (ours). Then run the container tests with them:
#
#   sudo sh scripts/container-check/build-standins.sh
#   BAM_CHECK_PYTHON_IMAGE=bam-standin/python:3.11-bookworm \
#   BAM_CHECK_POSTGRES_IMAGE=bam-standin/postgres:15-bookworm \
#       .venv/bin/python -m pytest tests/commands/test_container_image.py
#
# Needs root, debootstrap and a running Docker engine. The Python image is Debian bookworm's
# Python 3.11 with pip allowed to install system-wide (as in the official image, and like it
# without GNU OpenMP, which the Dockerfile installs); both images
# trust this machine's extra certificate authorities (a TLS-inspecting proxy's), so that pip
# inside a build reaches PyPI as the machine does.
set -eu
MIRROR=${MIRROR:-http://deb.debian.org/debian}
HERE=$(cd "$(dirname "$0")" && pwd)
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
ROOT="$WORK/rootfs"
debootstrap --variant=minbase \
    --include=python3,python3-venv,python3-pip,python-is-python3,ca-certificates \
    bookworm "$ROOT" "$MIRROR"
rm -f "$ROOT/usr/lib/python3.11/EXTERNALLY-MANAGED"
if ls /usr/local/share/ca-certificates/*.crt >/dev/null 2>&1; then
    cp /usr/local/share/ca-certificates/*.crt "$ROOT/usr/local/share/ca-certificates/"
    chroot "$ROOT" update-ca-certificates >/dev/null
fi
PATHS=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
tar -C "$ROOT" -c . | docker import \
    -c "ENV PATH=$PATHS LANG=C.UTF-8" -c 'CMD ["python3"]' \
    - bam-standin/python:3.11-bookworm
cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
chroot "$ROOT" sh -c 'apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
    --no-install-recommends postgresql-15 postgresql-client-15' >/dev/null
rm -f "$ROOT/etc/resolv.conf"
cp "$HERE/postgres-entrypoint.sh" "$ROOT/usr/local/bin/docker-entrypoint.sh"
chmod 755 "$ROOT/usr/local/bin/docker-entrypoint.sh"
tar -C "$ROOT" -c . | docker import \
    -c "ENV PATH=/usr/lib/postgresql/15/bin:$PATHS LANG=C.UTF-8 PGDATA=/var/lib/postgresql/data" \
    -c 'ENTRYPOINT ["/usr/local/bin/docker-entrypoint.sh"]' -c 'EXPOSE 5432' \
    - bam-standin/postgres:15-bookworm
echo "built bam-standin/python:3.11-bookworm and bam-standin/postgres:15-bookworm"
