#!/usr/bin/env bash
# Build the ballbot-vision Python base image locally, from Debian packages only.
#
# Why: the top-level Dockerfile starts FROM a normal public image (python:3.11-slim-bookworm).
# Where no container registry can be reached (an air-gapped robot, a lab network, CI without
# registry access) that image cannot be pulled. This script makes an equivalent one from the
# Debian archive that apt already uses on this host:
#
#   debootstrap --variant=minbase SUITE  +  python3 python3-venv ca-certificates tini
#   -> security/point-release upgrades -> docs, caches and apt lists removed
#   -> `tar | docker import` as ballbot-vision/python-base:<python>-<suite>
#
# Then build the project image on top of it:
#
#   deploy/build-base-image.sh
#   docker build --build-arg BASE_IMAGE=ballbot-vision/python-base:3.11-bookworm \
#                -t ballbot-vision:latest .
#
# Usage: deploy/build-base-image.sh [options]
#   --suite SUITE      Debian release to bootstrap (default: the host's VERSION_CODENAME if the
#                      host is Debian, else bookworm). Known: bookworm (Python 3.11),
#                      trixie (Python 3.13).
#   --tag TAG          image tag (default: ballbot-vision/python-base:<python>-<suite>)
#   --mirror URL       Debian mirror (default: read from the host's apt sources; env BASE_MIRROR)
#   --security URL     Debian security mirror (default: read from the host's apt sources;
#                      env BASE_SECURITY_MIRROR; "none" skips security updates)
#   --workdir DIR      where the rootfs is built (default: a fresh dir under ${TMPDIR:-/var/tmp});
#                      it is removed afterwards unless --keep-rootfs
#   --keep-rootfs      keep the rootfs directory (for inspection)
#   --force            rebuild even if TAG already exists
#   --print-tag        print the tag that would be built and exit
#   -h, --help         this text
#
# Needs: root (debootstrap and chroot), docker, debootstrap (installed with apt-get if missing
# and apt-get is available). Takes a few minutes; the image is about 130 MB (no pip cache,
# no docs, no apt lists).
#
# Idempotent: exits 0 at once when TAG already exists, unless --force.
# Nothing is written inside the repository.
set -euo pipefail

PROG=$(basename "$0")
log() { printf '[%s] %s\n' "$PROG" "$*" >&2; }
die() { printf '[%s] error: %s\n' "$PROG" "$*" >&2; exit 1; }
usage() { sed -n '2,/^set -euo/p' "$0" | sed -e '$d' -e 's/^# \{0,1\}//'; }

SUITE=""
TAG=""
MIRROR="${BASE_MIRROR:-}"
SECURITY="${BASE_SECURITY_MIRROR:-}"
WORKDIR=""
KEEP=0
FORCE=0
PRINT_TAG=0
PACKAGES="python3,python3-venv,ca-certificates"
OPTIONAL_PACKAGES="tini"

while [ $# -gt 0 ]; do
    case "$1" in
        --suite) SUITE=${2:?--suite needs a value}; shift 2 ;;
        --tag) TAG=${2:?--tag needs a value}; shift 2 ;;
        --mirror) MIRROR=${2:?--mirror needs a value}; shift 2 ;;
        --security) SECURITY=${2:?--security needs a value}; shift 2 ;;
        --workdir) WORKDIR=${2:?--workdir needs a value}; shift 2 ;;
        --keep-rootfs) KEEP=1; shift ;;
        --force) FORCE=1; shift ;;
        --print-tag) PRINT_TAG=1; shift ;;
        -h|--help) usage; exit 0 ;;
        *) die "unknown option: $1 (see --help)" ;;
    esac
done

# --- suite and tag ----------------------------------------------------------------------------
if [ -z "$SUITE" ]; then
    SUITE=bookworm
    if [ -r /etc/os-release ]; then
        # shellcheck disable=SC1091
        . /etc/os-release
        if [ "${ID:-}" = debian ] && [ -n "${VERSION_CODENAME:-}" ]; then
            SUITE=$VERSION_CODENAME
        fi
    fi
fi
case "$SUITE" in
    bookworm) PYVER=3.11 ;;
    trixie) PYVER=3.13 ;;
    *) PYVER="" ;;
esac
if [ -z "$TAG" ]; then
    [ -n "$PYVER" ] || die "unknown Python version for suite '$SUITE': pass --tag explicitly"
    TAG="ballbot-vision/python-base:${PYVER}-${SUITE}"
fi
if [ "$PRINT_TAG" = 1 ]; then
    echo "$TAG"
    exit 0
fi

# --- preconditions ----------------------------------------------------------------------------
command -v docker >/dev/null 2>&1 || die "docker not found: install the Docker engine first"
docker info >/dev/null 2>&1 || die "cannot talk to the Docker daemon (is it running? are you root or in the docker group?)"

if [ "$FORCE" = 0 ] && docker image inspect "$TAG" >/dev/null 2>&1; then
    log "$TAG already exists ($(docker image inspect -f '{{.Size}}' "$TAG" | awk '{printf "%.0f MB", $1/1e6}')); nothing to do (use --force to rebuild)"
    exit 0
fi

[ "$(id -u)" = 0 ] || die "must run as root (debootstrap and chroot need it); try: sudo $0 $*"

if ! command -v debootstrap >/dev/null 2>&1; then
    if command -v apt-get >/dev/null 2>&1; then
        log "debootstrap not found; installing it with apt-get"
        DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends debootstrap >&2 \
            || { apt-get update >&2 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends debootstrap >&2; } \
            || die "debootstrap is missing and 'apt-get install debootstrap' failed; install it by hand (Debian/Ubuntu package 'debootstrap')"
    else
        die "debootstrap is missing and this host has no apt-get; install debootstrap (it is a shell script, packaged by most distributions) and retry"
    fi
    command -v debootstrap >/dev/null 2>&1 || die "debootstrap still not found in PATH ($PATH) after installing it"
fi
[ -e "/usr/share/debootstrap/scripts/$SUITE" ] || die "this debootstrap does not know suite '$SUITE' (no /usr/share/debootstrap/scripts/$SUITE); upgrade debootstrap or pick another --suite"

# --- mirrors from the host's apt sources ----------------------------------------------------
# Prints "URI SUITE" for every deb source of the host, from one-line sources.list files and
# deb822 *.sources files. Disabled files (not ending in .list / .sources) are ignored.
host_apt_sources() {
    local f
    for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
        [ -r "$f" ] || continue
        # deb [options] URI SUITE COMPONENTS...
        sed -e 's/#.*//' -e 's/\[[^]]*\]//' "$f" | awk '$1 == "deb" && NF >= 3 { print $2, $3 }'
    done
    for f in /etc/apt/sources.list.d/*.sources; do
        [ -r "$f" ] || continue
        awk '
            function flush(   i, j, nu, ns, u, s) {
                if (types ~ /(^| )deb( |$)/ && enabled != "no") {
                    nu = split(uris, u, " "); ns = split(suites, s, " ")
                    for (i = 1; i <= nu; i++) for (j = 1; j <= ns; j++) print u[i], s[j]
                }
                types = ""; uris = ""; suites = ""; enabled = ""
            }
            /^[ \t]*#/ { next }
            /^[ \t]*$/ { flush(); next }
            {
                key = tolower($1); sub(/:$/, "", key); $1 = ""; sub(/^ +/, "")
                if (key == "types") types = $0
                else if (key == "uris") uris = $0
                else if (key == "suites") suites = $0
                else if (key == "enabled") enabled = tolower($0)
            }
            END { flush() }
        ' "$f"
    done
}

# Picks the URI of the first host source whose suite matches $1 exactly (e.g. bookworm,
# bookworm-security). Falls back to a source of another Debian suite with the same layout:
# a host running bookworm can still bootstrap trixie from its mirror.
pick_mirror() {
    local want=$1 alt_suffix=$2 uri suite
    uri=$(host_apt_sources | awk -v w="$want" '$2 == w { print $1; exit }')
    if [ -z "$uri" ] && [ -n "$alt_suffix" ]; then
        uri=$(host_apt_sources | awk -v s="$alt_suffix" '$2 ~ s { print $1; exit }')
    fi
    printf '%s' "${uri%/}"
}

if [ -z "$MIRROR" ]; then
    MIRROR=$(pick_mirror "$SUITE" '^[a-z]+$')
    [ -n "$MIRROR" ] || die "could not find a Debian mirror in /etc/apt/sources.list*; pass --mirror URL (or BASE_MIRROR)"
fi
if [ -z "$SECURITY" ]; then
    SECURITY=$(pick_mirror "${SUITE}-security" '-security$')
    [ -n "$SECURITY" ] || { log "no security mirror in the host's apt sources; building without ${SUITE}-security updates"; SECURITY=none; }
fi

# --- build ------------------------------------------------------------------------------------
START=$(date +%s)
if [ -z "$WORKDIR" ]; then
    WORKDIR=$(mktemp -d "${TMPDIR:-/var/tmp}/ballbot-base.XXXXXX")
else
    mkdir -p "$WORKDIR"
fi
ROOTFS="$WORKDIR/rootfs"
[ ! -e "$ROOTFS" ] || die "$ROOTFS already exists; remove it or pick another --workdir"

cleanup() {
    local rc=$?
    # Never leave a mount behind, even on failure (rm -rf would otherwise walk into /proc).
    for m in "$ROOTFS/proc" "$ROOTFS/sys" "$ROOTFS/dev/pts"; do
        if mountpoint -q "$m" 2>/dev/null; then umount -l "$m" || true; fi
    done
    if [ "$KEEP" = 1 ]; then
        log "rootfs kept in $ROOTFS"
    elif [ -d "$WORKDIR" ]; then
        rm -rf --one-file-system "$WORKDIR"
    fi
    exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# tini is optional: include it only if the suite has it (it does in bookworm and trixie).
INCLUDE=$PACKAGES
for p in $(echo "$OPTIONAL_PACKAGES" | tr ',' ' '); do
    INCLUDE="$INCLUDE,$p"
done

log "suite=$SUITE tag=$TAG packages=$INCLUDE"
log "mirror and security mirror taken from the host's apt sources (or --mirror/--security)"
log "debootstrap --variant=minbase into $ROOTFS (a few minutes)"
if ! debootstrap --variant=minbase --include="$INCLUDE" --components=main \
        "$SUITE" "$ROOTFS" "$MIRROR" >"$WORKDIR/debootstrap.log" 2>&1; then
    tail -n 30 "$WORKDIR/debootstrap.log" >&2 || true
    [ -r "$ROOTFS/debootstrap/debootstrap.log" ] && tail -n 30 "$ROOTFS/debootstrap/debootstrap.log" >&2
    KEEP=1
    die "debootstrap failed (log above; rootfs kept in $ROOTFS)"
fi

# apt sources of the image: the same mirrors, so `apt-get install` works in derived images.
rm -f "$ROOTFS/etc/apt/sources.list"
{
    printf 'Types: deb\nURIs: %s\nSuites: %s %s-updates\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
        "$MIRROR" "$SUITE" "$SUITE"
    if [ "$SECURITY" != none ]; then
        printf '\nTypes: deb\nURIs: %s\nSuites: %s-security\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
            "$SECURITY" "$SUITE"
    fi
} >"$ROOTFS/etc/apt/sources.list.d/debian.sources"

# Container conventions, as in Debian's official slim images: no docs/man/locales from later
# installs, no recommends, no apt caches left in layers, no service starts in the chroot.
cat >"$ROOTFS/etc/dpkg/dpkg.cfg.d/01-container-slim" <<'EOF'
# Added by ballbot-vision deploy/build-base-image.sh: keep container images small.
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
path-exclude /usr/share/lintian/*
EOF
cat >"$ROOTFS/etc/apt/apt.conf.d/01-container" <<'EOF'
// Added by ballbot-vision deploy/build-base-image.sh
APT::Install-Recommends "false";
APT::Install-Suggests "false";
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Binary::apt::APT::Keep-Downloaded-Packages "false";
Acquire::Languages "none";
Acquire::GzipIndexes "true";
EOF
printf '#!/bin/sh\nexit 101\n' >"$ROOTFS/usr/sbin/policy-rc.d"
chmod 755 "$ROOTFS/usr/sbin/policy-rc.d"

log "applying ${SUITE}-updates and ${SUITE}-security upgrades in the chroot"
cp /etc/resolv.conf "$ROOTFS/etc/resolv.conf"
mount -t proc proc "$ROOTFS/proc"
if ! chroot "$ROOTFS" /bin/sh -c '
        set -e
        export DEBIAN_FRONTEND=noninteractive LC_ALL=C
        apt-get update -q
        apt-get -y -q -o Dpkg::Options::=--force-confold dist-upgrade
        apt-get -y -q autoremove --purge
        apt-get clean
    ' >>"$WORKDIR/debootstrap.log" 2>&1; then
    tail -n 30 "$WORKDIR/debootstrap.log" >&2
    KEEP=1
    die "apt-get upgrade in the chroot failed (log above)"
fi
umount "$ROOTFS/proc"

# Sanity: the Python the tag promises, with venv + ensurepip (python3-venv) and TLS roots.
GOT=$(chroot "$ROOTFS" /usr/bin/python3 -c 'import sys, venv, ensurepip, ssl; print("%d.%d" % sys.version_info[:2])') \
    || die "python3 in the rootfs cannot import venv/ensurepip/ssl"
if [ -n "$PYVER" ] && [ "$GOT" != "$PYVER" ]; then
    die "suite $SUITE gave Python $GOT, expected $PYVER (tag $TAG would lie)"
fi
TINI=no
[ -x "$ROOTFS/usr/bin/tini" ] && TINI=yes

log "trimming the rootfs"
# Docker bind-mounts its own resolv.conf, hosts and hostname at run time.
: >"$ROOTFS/etc/resolv.conf"
rm -rf "$ROOTFS"/var/lib/apt/lists/* \
       "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/var/cache/apt/archives/*.deb \
       "$ROOTFS"/var/cache/debconf/*-old "$ROOTFS"/var/lib/dpkg/*-old \
       "$ROOTFS"/var/log/* "$ROOTFS"/tmp/* "$ROOTFS"/var/tmp/* \
       "$ROOTFS"/debootstrap \
       "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/* "$ROOTFS"/usr/share/lintian
find "$ROOTFS/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete 2>/dev/null || true
find "$ROOTFS/usr/share/doc" -mindepth 1 -type d -empty -delete 2>/dev/null || true
find "$ROOTFS/usr/share/locale" -mindepth 1 -maxdepth 1 -not -name locale.alias -exec rm -rf {} + 2>/dev/null || true
: >"$ROOTFS/etc/machine-id"

log "importing into Docker as $TAG"
CREATED=$(date -u +%Y-%m-%dT%H:%M:%SZ)
tar --numeric-owner --xattrs -C "$ROOTFS" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change "LABEL org.opencontainers.image.title=ballbot-vision-python-base" \
    --change "LABEL org.opencontainers.image.description=\"Debian ${SUITE} minbase, python3 ${GOT}, venv, ca-certificates, tini: ${TINI}; built by deploy/build-base-image.sh\"" \
    --change "LABEL org.opencontainers.image.created=${CREATED}" \
    --change "LABEL org.opencontainers.image.base.name=debian:${SUITE}" \
    --change 'CMD ["python3"]' \
    - "$TAG" >/dev/null

SIZE=$(docker image inspect -f '{{.Size}}' "$TAG" | awk '{printf "%.0f MB", $1/1e6}')
log "built $TAG: Python $GOT, tini: $TINI, $SIZE, in $(( $(date +%s) - START )) s"
log "next: docker build --build-arg BASE_IMAGE=$TAG -t ballbot-vision:latest ."
echo "$TAG"
