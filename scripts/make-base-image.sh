#!/usr/bin/env bash
# A base image for the Dockerfile's BASE_IMAGE, made from Debian's own packages, for hosts that
# reach a Debian mirror but no image registry (python:3.11-slim cannot be pulled there):
# Debian 12's Python 3.11 with venv (whose ensurepip gives the image's venv its pip), and CA
# certificates. Needs root, debootstrap and a
# running Docker engine; takes about a minute and 300 MB.
#
#   scripts/make-base-image.sh [IMAGE] [MIRROR]
#     IMAGE   the tag to give it (default overtake-base:bookworm)
#     MIRROR  a Debian mirror (default: the first of this host's apt sources that serves
#             Debian, else http://deb.debian.org/debian)
#   then: docker build --build-arg BASE_IMAGE=overtake-base:bookworm ...
#     or: OVERTAKE_BASE_IMAGE=overtake-base:bookworm docker compose up --build
set -euo pipefail
image="${1:-overtake-base:bookworm}"
mirror="${2:-}"
if [[ -z "$mirror" ]]; then
  # deb822 .sources files ("URIs: ...") and one-line sources.list entries ("deb URI suite ...").
  mirror="$(
    { grep -hs '^URIs:' /etc/apt/sources.list.d/*.sources | awk '{print $2}'
      grep -hs '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list | awk '{print $2}'
    } | grep -v -- '-security' | head -n 1 || true
  )"
  mirror="${mirror:-http://deb.debian.org/debian}"
fi
for tool in debootstrap docker; do
  command -v "$tool" >/dev/null || { echo "make-base-image: $tool is not installed" >&2; exit 2; }
done
if [[ "$(id -u)" != 0 ]]; then
  echo "make-base-image: debootstrap needs root" >&2
  exit 2
fi
root="$(mktemp -d)"
trap 'rm -rf "$root"' EXIT
echo "make-base-image: Debian bookworm from $mirror into $image" >&2
debootstrap --variant=minbase \
  --include=python3,python3-venv,ca-certificates \
  bookworm "$root" "$mirror" >"$root.log" 2>&1 || {
    tail -n 20 "$root.log" >&2
    echo "make-base-image: debootstrap failed (log above)" >&2
    exit 1
  }
rm -f "$root.log"
# What an image needs and debootstrap leaves: no apt lists or caches in the layer.
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/archives/*.deb
tar -C "$root" -c . | docker import \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' \
  --change 'CMD ["python3"]' \
  - "$image" >/dev/null
echo "$image"
