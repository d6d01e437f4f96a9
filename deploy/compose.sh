#!/usr/bin/env bash
# Docker Compose for this project, whichever this machine has: `docker compose` (v2, the plugin) or
# `docker-compose` (v1.29+), with the repository's docker-compose.yml from any working directory.
# README's Docker lines use it so that they work as written on either (deploy/docker-up.sh makes the
# same choice).
#
# Usage: deploy/compose.sh ARGS...          the arguments of `docker compose`, e.g.
#   deploy/compose.sh up -d --scale disparity=3
#   deploy/compose.sh --profile viewer up -d
#   COMPOSE_PROFILES=viewer,ros2 deploy/compose.sh up -d
#   deploy/compose.sh down
#   deploy/compose.sh --which                 print the compose command it uses, and nothing else
# As root or as a member of the docker group; anyone else is told to use sudo when compose fails.
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"

if docker compose version >/dev/null 2>&1; then
    COMPOSE=(docker compose)
elif command -v docker-compose >/dev/null 2>&1; then
    COMPOSE=(docker-compose)
else
    echo "compose.sh: neither 'docker compose' nor 'docker-compose' is installed (Debian: apt-get install docker-compose)" >&2
    exit 127
fi
if [ "${1:-}" = "--which" ]; then
    echo "${COMPOSE[*]}"
    exit 0
fi

status=0
"${COMPOSE[@]}" "$@" || status=$?
if [ "$status" != 0 ] && [ "$(id -u)" != 0 ] && [ -z "${DOCKER_HOST:-}" ] && [ -e /var/run/docker.sock ] \
        && [ ! -w /var/run/docker.sock ]; then
    echo "compose.sh: the Docker engine needs root or the docker group: sudo deploy/compose.sh $*" >&2
fi
exit "$status"
