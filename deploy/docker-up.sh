#!/usr/bin/env bash
# From a fresh clone to the pipeline in containers, in one go, without a container registry:
#
#   1. checks   a Docker engine that answers, and a compose command: `docker compose` (v2) or
#               `docker-compose` (v1.29+), whichever this machine has
#   2. base     the Python base image from Debian packages (deploy/build-base-image.sh; needs root
#               and debootstrap, once; skipped when the tag exists)
#   3. wheels   every pinned wheel into build/wheelhouse (deploy/fetch-wheels.sh, with the host's
#               pip and trust store: pip inside a build may not verify TLS behind a proxy; skipped
#               when the wheelhouse already holds every pin)
#   4. image    docker build -> ballbot-vision:latest (cached layers reused; a failed build leaves no
#               stopped container and no untagged image behind)
#   5. up       `docker compose up ARGS...` with the top-level docker-compose.yml
# Step 1 also makes the calibration key the robot's containers share (BALLBOT_CALIBRATION_KEY),
# once (deploy/calibration-key.sh): kept in .env and deploy/.env, which compose reads.
#
# Usage: deploy/docker-up.sh [--build-only] [--rebuild-base] [--] [ARGS for `compose up`...]
#   deploy/docker-up.sh                       # build what is missing, then the pipeline in the foreground
#   deploy/docker-up.sh -d --scale disparity=3
#   deploy/docker-up.sh --build-only          # steps 1-4 (what CI and the docker tests run)
#   --rebuild-base      rebuild the base image even if it exists (security updates)
# Environment:
#   BASE_IMAGE          base image (default ballbot-vision/python-base:3.11-bookworm, built in step 2;
#                       e.g. python:3.11-slim-bookworm where a registry is reachable: step 2 is skipped)
#   BALLBOT_IMAGE       the image to build and run (default ballbot-vision:latest)
#   DOCKER_UP_LOGS      where each step's full output goes (default build/docker-up/)
# Every step prints what it does and how long it took; a failing step says which one, why, the
# last lines of its log and where the whole log is; the exit status is that step's number (1-5).
set -euo pipefail

HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(dirname "$HERE")
cd "$ROOT"

LOCAL_BASE=$("$HERE/build-base-image.sh" --print-tag 2>/dev/null || echo ballbot-vision/python-base:3.11-bookworm)
export BASE_IMAGE=${BASE_IMAGE:-$LOCAL_BASE}
export BALLBOT_IMAGE=${BALLBOT_IMAGE:-ballbot-vision:latest}
LOGS=${DOCKER_UP_LOGS:-$ROOT/build/docker-up}
BUILD_ONLY=0
REBUILD_BASE=0
UP_ARGS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --build-only) BUILD_ONLY=1; shift ;;
        --rebuild-base) REBUILD_BASE=1; shift ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed -e '$d' -e 's/^# \{0,1\}//'; exit 0 ;;
        --) shift; UP_ARGS+=("$@"); break ;;
        *) UP_ARGS+=("$1"); shift ;;
    esac
done

STEP=0
STEP_NAME=""
STEP_T0=0
T0=$(date +%s)
TOTAL=5
[ "$BUILD_ONLY" = 1 ] && TOTAL=4
mkdir -p "$LOGS"

say() { printf 'docker-up: %s\n' "$*" >&2; }
step() {  # step N NAME: what it does
    STEP=$1; STEP_NAME=$2; STEP_T0=$(date +%s)
    say "[$STEP/$TOTAL] $STEP_NAME: $3"
}
done_step() { say "[$STEP/$TOTAL] $STEP_NAME: $1 ($(( $(date +%s) - STEP_T0 )) s)"; }
fail() {  # fail WHY [LOG]
    say "error in step $STEP/$TOTAL ($STEP_NAME): $1"
    if [ -n "${2:-}" ] && [ -s "$2" ]; then
        say "last lines of $2:"
        tail -n 25 "$2" | sed 's/^/    /' >&2
        say "whole log: $2"
    fi
    exit "$STEP"
}

# run_logged LOG CMD...: the command's output into LOG; a line of progress every 20 s.
run_logged() {
    local log=$1; shift
    : >"$log"
    "$@" >>"$log" 2>&1 &
    local pid=$! start=$SECONDS next=$((SECONDS + 20))
    while kill -0 "$pid" 2>/dev/null; do
        sleep 1
        if [ "$SECONDS" -ge "$next" ]; then
            say "      ... $((SECONDS - start)) s: $(tail -n 1 "$log" | cut -c1-110)"
            next=$((SECONDS + 20))
        fi
    done
    wait "$pid"
}

# --- cleanup of what a failed build leaves: stopped build containers, untagged images ---------
dangling() { docker images -q --no-trunc -f dangling=true 2>/dev/null | sort -u; }
BEFORE_DANGLING=""
cleanup_build() {
    local now new
    now=$(dangling)
    new=$(comm -13 <(printf '%s\n' "$BEFORE_DANGLING") <(printf '%s\n' "$now") | sed '/^$/d')
    if [ -n "$new" ]; then
        # shellcheck disable=SC2086
        docker rmi $new >/dev/null 2>&1 || true
    fi
}
on_exit() {
    local rc=$?
    if [ "$rc" != 0 ] && [ "$STEP" = 4 ]; then
        cleanup_build
        say "removed what the failed build left behind (stopped containers, untagged images)"
    fi
}
trap on_exit EXIT
trap 'say "interrupted"; exit 130' INT TERM

# --- 1. checks ----------------------------------------------------------------------------------
step 1 checks "Docker engine and compose command"
command -v docker >/dev/null 2>&1 || fail "no docker command: install the Docker engine (Debian: apt-get install docker.io)"
if ! info=$(docker info --format '{{.ServerVersion}}' 2>&1); then
    fail "the Docker engine does not answer: $(printf '%s' "$info" | tail -n 1) (is the daemon running? are you root or in the docker group?)"
fi
if docker compose version >/dev/null 2>&1; then
    COMPOSE=(docker compose)
elif command -v docker-compose >/dev/null 2>&1; then
    COMPOSE=(docker-compose)
    v=$(docker-compose version --short 2>/dev/null || echo 0)
    case "$v" in
        1.2[7-9]*|1.[3-9]*|[2-9]*) ;;
        *) fail "docker-compose $v is too old for docker-compose.yml (needs 1.27 or newer, or Docker's compose plugin)" ;;
    esac
else
    fail "neither 'docker compose' nor 'docker-compose' is installed (Debian: apt-get install docker-compose)"
fi
done_step "engine $info, ${COMPOSE[*]} $("${COMPOSE[@]}" version --short 2>/dev/null || echo '?')"

# The robot's containers share one calibration key, which the compose files require: made once
# and kept in .env and deploy/.env (deploy/calibration-key.sh).
"$HERE/calibration-key.sh" 2>&1 | sed 's/^/docker-up:       /' >&2 || fail "deploy/calibration-key.sh could not keep the calibration key"

# --- 2. base image ------------------------------------------------------------------------------
step 2 base "$BASE_IMAGE"
if [ "$REBUILD_BASE" = 0 ] && docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
    done_step "present"
elif [ "$BASE_IMAGE" != "$LOCAL_BASE" ]; then
    log="$LOGS/2-base.log"
    run_logged "$log" docker pull "$BASE_IMAGE" \
        || fail "cannot pull $BASE_IMAGE (no registry? unset BASE_IMAGE to build the base from Debian packages)" "$log"
    done_step "pulled"
else
    if [ "$(id -u)" != 0 ]; then
        fail "$BASE_IMAGE is missing and building it needs root (debootstrap, chroot): run 'sudo deploy/build-base-image.sh' once, then this script again"
    fi
    say "      building from Debian packages with debootstrap (a few minutes)"
    log="$LOGS/2-base.log"
    force=()
    [ "$REBUILD_BASE" = 1 ] && force=(--force)
    run_logged "$log" "$HERE/build-base-image.sh" "${force[@]}" --tag "$BASE_IMAGE" \
        || fail "deploy/build-base-image.sh failed" "$log"
    done_step "built"
fi

# --- 3. wheels ----------------------------------------------------------------------------------
step 3 wheels "pinned wheels in build/wheelhouse"
missing_wheels() {  # prints the pins of deploy/*constraints.txt without a wheel in build/wheelhouse
    python3 - "$HERE/constraints.txt" "$HERE/build-constraints.txt" "$ROOT/build/wheelhouse" <<'EOF'
import re, sys
from pathlib import Path
norm = lambda s: re.sub(r"[-_.]+", "_", s).lower()
have = set()
for w in Path(sys.argv[3]).glob("*.whl"):
    parts = w.name.split("-")
    have.add((norm(parts[0]), parts[1]))
for f in sys.argv[1:3]:
    for line in Path(f).read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = (x.strip() for x in line.split(";")[0].split("=="))
            if (norm(name), version) not in have:
                print(f"{name}=={version}")
EOF
}
command -v python3 >/dev/null 2>&1 || fail "python3 is needed on the host to fetch the wheels"
gaps=$(missing_wheels)
if [ -z "$gaps" ]; then
    done_step "all $(grep -c '==' "$HERE/constraints.txt" "$HERE/build-constraints.txt" | awk -F: '{s+=$2} END {print s}') pins present"
else
    say "      fetching $(printf '%s\n' "$gaps" | wc -l) wheel(s): $(printf '%s ' $gaps | cut -c1-120)"
    log="$LOGS/3-wheels.log"
    run_logged "$log" "$HERE/fetch-wheels.sh" \
        || fail "deploy/fetch-wheels.sh could not download the pinned wheels (is PyPI reachable from this host?)" "$log"
    gaps=$(missing_wheels)
    [ -z "$gaps" ] || fail "still no wheel for: $gaps"
    done_step "fetched"
fi

# --- 4. image -----------------------------------------------------------------------------------
step 4 image "docker build -> $BALLBOT_IMAGE (from $BASE_IMAGE)"
BEFORE_DANGLING=$(dangling)
log="$LOGS/4-image.log"
# --force-rm: no stopped container is left even when a step fails; the previous image of the tag,
# untagged by the build, and any untagged layer of a failed build are removed afterwards.
if ! run_logged "$log" docker build --force-rm --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$BALLBOT_IMAGE" "$ROOT"; then
    why="docker build failed"
    grep -q "pyproject.toml are not satisfied" "$log" && why="$why: the pinned dependencies no longer match pyproject.toml (run deploy/lock-constraints.sh and commit deploy/*constraints.txt)"
    fail "$why" "$log"
fi
cleanup_build
done_step "$(docker image inspect -f '{{.Size}}' "$BALLBOT_IMAGE" | awk '{printf "%.0f MB", $1/1e6}')"

say "built in $(( $(date +%s) - T0 )) s"
if [ "$BUILD_ONLY" = 1 ]; then
    exit 0
fi

# --- 5. up --------------------------------------------------------------------------------------
step 5 up "${COMPOSE[*]} up ${UP_ARGS[*]:-}"
say "      obstacles from the host: ballbot-vision watch --connect tcp/127.0.0.1:${ROUTER_PORT:-7447}"
trap - EXIT
exec "${COMPOSE[@]}" up "${UP_ARGS[@]}"
