#!/usr/bin/env bash
# The calibration key the robot's containers share (BALLBOT_CALIBRATION_KEY): capture signs the
# calibrations it publishes (a ROS camera's CameraInfo, a recording's), rectify takes signed ones
# and refuses anyone else's jumps (common/signing.py). The compose files have no default for it (a
# key written in a public file would sign for anyone); this makes one, once, and keeps it in
#   .env          read by compose for docker-compose.yml
#   deploy/.env   read by compose for deploy/robot.compose.yml
# for every compose command (up, down, logs). A key already set (BALLBOT_CALIBRATION_KEY) or kept
# in either file is used and never replaced; the files are created mode 0600 (owned by the user
# behind sudo) and are git-ignored and docker-ignored. The key is never printed.
#
# Usage: deploy/calibration-key.sh          (deploy/docker-up.sh runs it in its step 1)
set -euo pipefail

HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(dirname "$HERE")

key_in() {  # the key kept in an env file, if any
    if [ -f "$1" ]; then sed -n 's/^BALLBOT_CALIBRATION_KEY=\(..*\)$/\1/p' "$1" | tail -n 1; fi
}

key=${BALLBOT_CALIBRATION_KEY:-$(key_in "$ROOT/.env")}
key=${key:-$(key_in "$HERE/.env")}
made=""
if [ -z "$key" ]; then
    key=$(od -An -tx1 -N32 /dev/urandom | tr -d ' \n')
    made="made one, "
fi
for env_file in "$ROOT/.env" "$HERE/.env"; do
    [ -n "$(key_in "$env_file")" ] && continue
    new=1
    [ -e "$env_file" ] && new=""
    # a last line without its newline would swallow ours
    if [ -s "$env_file" ] && [ -n "$(tail -c 1 "$env_file")" ]; then echo >>"$env_file"; fi
    if ! (umask 077; printf 'BALLBOT_CALIBRATION_KEY=%s\n' "$key" >>"$env_file"); then
        echo "calibration-key: cannot write $env_file" >&2
        exit 1
    fi
    # under sudo, the file belongs to the user who ran it, so their later `docker compose down` reads it
    if [ -n "$new" ] && [ -n "${SUDO_USER:-}" ]; then chown "$SUDO_USER" "$env_file" || true; fi
done
echo "calibration key: ${made}kept in .env and deploy/.env (the robot's containers share it; keep it private)" >&2
