# ballbot-vision: one image for every service (capture, rectify, disparity, segmenter, router, and
# the optional ones: every runtime extra of pyproject.toml is installed, see deploy/image-extras.py).
#
#   deploy/docker-up.sh --build-only       # base image, wheels and this build, in order, no registry
#   docker run --rm ballbot-vision --help
#   docker compose up                      # the whole pipeline, see docker-compose.yml
#
# By hand: the base image comes from Debian packages (no container registry needed), the pinned
# wheels from the host (pip inside a build may not verify TLS behind an intercepting proxy):
#
#   deploy/build-base-image.sh             # -> ballbot-vision/python-base:3.11-bookworm (root, once)
#   deploy/fetch-wheels.sh                 # -> build/wheelhouse/: the build installs with --no-index
#   docker build -t ballbot-vision .
#
# Where a registry is reachable: --build-arg BASE_IMAGE=python:3.11-slim-bookworm.
# Python dependencies are pinned by deploy/constraints.txt (regenerate with
# deploy/lock-constraints.sh after changing pyproject.toml). Only classic-builder features are
# used, so it builds with and without BuildKit.

ARG BASE_IMAGE=ballbot-vision/python-base:3.11-bookworm

# ---------------------------------------------------------------------------------------------
# build: a venv in /opt/venv with the pinned dependencies and the project wheel
# ---------------------------------------------------------------------------------------------
FROM ${BASE_IMAGE} AS build

ENV PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_ROOT_USER_ACTION=ignore \
    LANG=C.UTF-8

# 1. Dependencies: the slow layer, rebuilt only when the pins change. The bracket glob makes
#    build/wheelhouse optional (its wheels, if any, land next to the constraint files).
COPY deploy/constraints.txt deploy/build-constraints.txt build/wheelhous[e] /tmp/pip/
RUN set -eu; \
    if ls /tmp/pip/*.whl >/dev/null 2>&1; then \
        echo "installing from the local wheelhouse only (build/wheelhouse, --no-index)"; \
        export PIP_NO_INDEX=1 PIP_FIND_LINKS=/tmp/pip; \
    fi; \
    python3 -m venv /opt/venv; \
    /opt/venv/bin/pip install --only-binary=:all: -r /tmp/pip/constraints.txt; \
    python3 -m venv /opt/buildtools; \
    /opt/buildtools/bin/pip install -r /tmp/pip/build-constraints.txt

# 2. The project with the image's extras: build a wheel (non-editable) and install it without
#    touching the index, so every requirement (extras included) must already be there from the
#    pins; then `pip check`. If this fails after a dependency change, run
#    deploy/lock-constraints.sh and commit deploy/constraints.txt. Dropped from the runtime venv:
#    pip and setuptools, and the test suites of numpy and scipy (never imported at run time).
COPY . /src
RUN set -eu; \
    /opt/buildtools/bin/pip wheel --no-deps --no-build-isolation --no-index -w /tmp/dist /src; \
    extras=$(python3 /src/deploy/image-extras.py /src/pyproject.toml); \
    echo "installing ballbot-vision with extras: ${extras:-none}"; \
    { /opt/venv/bin/pip install --no-index --find-links /tmp/dist "ballbot-vision${extras:+[$extras]}" \
      && /opt/venv/bin/pip check; } || { \
        echo "dependencies of pyproject.toml are not satisfied by deploy/constraints.txt:" \
             "run deploy/lock-constraints.sh and commit the result" >&2; exit 1; }; \
    /opt/venv/bin/ballbot-vision --help >/dev/null; \
    find /opt/venv/lib -depth -type d -name tests \
        \( -path '*/site-packages/numpy/*' -o -path '*/site-packages/scipy/*' \) \
        -exec rm -rf {} +; \
    /opt/venv/bin/python -m pip uninstall -q -y pip setuptools; \
    /opt/venv/bin/python -c 'import cv2, numpy, scipy, zenoh, pydantic, msgpack, yaml, ballbot_vision'

# ---------------------------------------------------------------------------------------------
# runtime: base image + venv + a non-root user
# ---------------------------------------------------------------------------------------------
FROM ${BASE_IMAGE} AS runtime

ARG BASE_IMAGE
LABEL org.opencontainers.image.title="ballbot-vision" \
      org.opencontainers.image.description="Stereo obstacle detection for a Ballbot as Zenoh microservices (capture, rectify, disparity, segmenter, router)" \
      org.opencontainers.image.licenses="MIT" \
      org.opencontainers.image.base.name="${BASE_IMAGE}"

# tini as PID 1 forwards SIGTERM (docker stop) to the service and reaps children. The base image
# from deploy/build-base-image.sh has it; the public python image gets it from Debian.
RUN if ! command -v tini >/dev/null 2>&1; then \
        apt-get update \
        && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends tini \
        && rm -rf /var/lib/apt/lists/*; \
    fi; \
    tini --version

# Non-root user. It is in the image's 'video' group for /dev/video*; compose files add the host's
# video GID too (group_add), since the device node carries the host's numbers.
RUN groupadd --system --gid 10001 ballbot \
    && useradd --system --uid 10001 --gid ballbot --groups video \
               --home-dir /var/lib/ballbot-vision --create-home --shell /usr/sbin/nologin ballbot

COPY --from=build /opt/venv /opt/venv

ENV VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    LANG=C.UTF-8

USER 10001:10001
WORKDIR /var/lib/ballbot-vision
# Zenoh router (only the `run router` container listens).
EXPOSE 7447/tcp

ENTRYPOINT ["tini", "--", "ballbot-vision"]
CMD ["run", "capture"]
