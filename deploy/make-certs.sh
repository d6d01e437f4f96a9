#!/usr/bin/env bash
# Make the keys, certificates and passwords for the robot router's external (tls/) endpoint.
#
# Output (default deploy/certs/, git-ignored and excluded from the Docker build context; never
# commit it, never bake it into an image: the compose files mount it read-only):
#   ca.pem, ca.key            a private CA for this robot (ca.key stays on the machine that ran this)
#   router.pem, router.key    the router's server certificate, SANs = the robot's names/addresses
#   <client>.pem, .key        one client certificate per offboard PC or user (mutual TLS)
#   users.txt                 the router's user/password dictionary: users worker and viewer
#   <client>.json5            a complete Zenoh client config for that client: deploy/zenoh/client.json5
#                             with its certificate and its role's user and password filled in.
#                             An offboard PC needs ca.pem, <client>.pem, <client>.key, <client>.json5.
#
# Usage: deploy/make-certs.sh [--out DIR] [--name DNS_OR_IP ...] [--client NAME[:ROLE] ...]
#                             [--days N] [--certs-path PATH] [--force]
#   --out DIR        output folder (default: deploy/certs next to this script)
#   --name N         a name or IP address offboard PCs use to reach the robot; repeatable. Goes
#                    into the router certificate's subjectAltName (clients verify it). Default:
#                    this machine's hostname, localhost, 127.0.0.1 and ::1.
#   --client N[:R]   a client certificate with CN N that logs in as role R (worker or viewer;
#                    default: N if it is a role name, else worker); repeatable, e.g. one per
#                    offboard PC: --client pc1 --client pc2 --client planner:viewer.
#                    Default: worker and viewer.
#   --days N         validity in days (default 825)
#   --certs-path P   where clients will find these files, written into <client>.json5
#                    (default /etc/zenoh-certs, where the compose files mount them)
#   --force          replace existing files (a new CA invalidates every certificate given out)
#
# Roles (see deploy/zenoh/router.json5, access_control): worker = offboard disparity worker
# (reads its work items, publishes disparity maps, receipts, stats, liveliness); viewer = reads
# obstacle lists, stats and liveliness only (planner, `ballbot-vision watch`/`status`). Only the
# robot's own services, on the router's internal endpoint, may publish obstacles or read frames
# other than a worker's own work items.
#
# File modes: keys and users.txt are 0640 and, when run as root, group 10001 (the image's user),
# so the containers can read them. Otherwise run: sudo chgrp 10001 DIR/*.key DIR/users.txt DIR/*.json5
set -euo pipefail

HERE=$(cd "$(dirname "$0")" && pwd)
OUT="$HERE/certs"
DAYS=825
FORCE=0
CERTS_PATH=/etc/zenoh-certs
NAMES=()
CLIENTS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --out) OUT=${2:?}; shift 2 ;;
        --name) NAMES+=("${2:?}"); shift 2 ;;
        --client) CLIENTS+=("${2:?}"); shift 2 ;;
        --days) DAYS=${2:?}; shift 2 ;;
        --certs-path) CERTS_PATH=${2:?}; shift 2 ;;
        --force) FORCE=1; shift ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed -e '$d' -e 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "unknown option: $1" >&2; exit 2 ;;
    esac
done
[ ${#NAMES[@]} -gt 0 ] || NAMES=("$(hostname)" localhost 127.0.0.1 ::1)
[ ${#CLIENTS[@]} -gt 0 ] || CLIENTS=(worker viewer)
command -v openssl >/dev/null || { echo "make-certs: openssl not found (apt-get install openssl)" >&2; exit 1; }

mkdir -p "$OUT"
chmod 0750 "$OUT"
if [ -e "$OUT/ca.pem" ] && [ "$FORCE" = 0 ]; then
    echo "make-certs: $OUT/ca.pem exists; --force replaces everything in $OUT" >&2
    exit 1
fi
umask 027
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# The CA.
key "$OUT/ca.key"
openssl req -x509 -new -key "$OUT/ca.key" -sha256 -days "$DAYS" -subj "/CN=ballbot-vision robot CA" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -out "$OUT/ca.pem"

# sign NAME CN EXTFILE
sign() {
    openssl req -new -key "$OUT/$1.key" -subj "/CN=$2" -out "$TMP/$1.csr"
    openssl x509 -req -in "$TMP/$1.csr" -CA "$OUT/ca.pem" -CAkey "$OUT/ca.key" -CAcreateserial \
        -CAserial "$TMP/ca.srl" -days "$DAYS" -sha256 -extfile "$3" -out "$OUT/$1.pem" 2>/dev/null
}

# The router: a server certificate whose SANs are every name clients may use for the robot.
san=""
for n in "${NAMES[@]}"; do
    if [[ "$n" =~ ^[0-9.]+$ || "$n" == *:* ]]; then san+="IP:$n,"; else san+="DNS:$n,"; fi
done
cat >"$TMP/router.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth
subjectAltName=${san%,}
EOF
key "$OUT/router.key"
sign router "${NAMES[0]}" "$TMP/router.ext"

# Users: one password per role in the router's dictionary (the router's ACL names these users).
: >"$OUT/users.txt"
for role in worker viewer; do
    echo "$role:$(openssl rand -hex 24)" >>"$OUT/users.txt"
done
# Clients: a certificate each (CN = its name, for mutual TLS) and a rendered Zenoh config that
# logs in as its role's user.
for c in "${CLIENTS[@]}"; do
    name=${c%%:*}
    role=${c#*:}
    [ "$role" != "$c" ] || { case "$name" in worker|viewer) role=$name ;; *) role=worker ;; esac; }
    [[ "$name" =~ ^[A-Za-z0-9_.-]+$ ]] || { echo "make-certs: bad client name $name" >&2; exit 2; }
    case "$role" in worker|viewer) ;; *) echo "make-certs: unknown role $role (worker or viewer)" >&2; exit 2 ;; esac
    printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" \
        "extendedKeyUsage=clientAuth" "subjectAltName=DNS:$name" >"$TMP/$name.ext"
    key "$OUT/$name.key"
    sign "$name" "$name" "$TMP/$name.ext"
    password=$(grep "^$role:" "$OUT/users.txt" | cut -d: -f2)
    sed -e "s|@CERTS@|$CERTS_PATH|g" -e "s/@USER@/$role/g" -e "s/@PASSWORD@/$password/g" -e "s/@CLIENT@/$name/g" \
        "$HERE/zenoh/client.json5" >"$OUT/$name.json5"
done

chmod 0644 "$OUT"/*.pem
chmod 0640 "$OUT"/*.key "$OUT/users.txt" "$OUT"/*.json5
chmod 0600 "$OUT/ca.key"   # signs new certificates: for the admin only, never for a container
if [ "$(id -u)" = 0 ]; then
    for f in "$OUT"/*.key "$OUT/users.txt" "$OUT"/*.json5; do
        [ "$f" = "$OUT/ca.key" ] || chgrp 10001 "$f"
    done
    chgrp 10001 "$OUT"
fi
echo "make-certs: wrote $OUT: CA, router certificate for ${NAMES[*]}; clients: ${CLIENTS[*]}" >&2
