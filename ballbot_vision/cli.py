"""`ballbot-vision`: the one entry point (see README for every command)."""
from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys

from common.errors import BallbotError
from common.settings import MountSettings, add_settings_arguments, load_settings
from common.supervisor import PIPELINE, SERVICES, stage_nice
from common.zenoh_session import DEFAULT_ROUTER, ZenohOptions, add_zenoh_arguments, options_from_args

log = logging.getLogger("ballbot")

# Modules that add their own subcommands: each has register(sub, common), where `common(parser)`
# adds --robot-id, --config and the Zenoh options to a parser and returns it.
COMMAND_MODULES: list[str] = [
    "ballbot_vision.calibration_commands",
    "ballbot_vision.segmenter_commands",
    "ballbot_vision.disparity_commands",
    "ballbot_vision.sample_commands",
    "ballbot_vision.mcap_commands",
]


def service_module(name: str):
    module, settings = SERVICES[name]
    m = importlib.import_module(module)
    return m, getattr(m, settings)


def robot_id(args: argparse.Namespace) -> str:
    return args.robot_id or os.environ.get("BALLBOT_ROBOT_ID") or "ballbot"


def config_file(args: argparse.Namespace) -> str | None:
    return getattr(args, "config", None) or os.environ.get("BALLBOT_CONFIG")


def zenoh_options(args: argparse.Namespace, service: str | None = None) -> ZenohOptions:
    o = options_from_args(args)
    if service == "router":
        # A router listens where the others connect; it connects out only when told to.
        explicit_listen = getattr(args, "listen", None) or os.environ.get("BALLBOT_LISTEN")
        o.mode = "router"
        # With --zenoh-config and no --listen/BALLBOT_LISTEN, the file's listen endpoints stand.
        o.listen = o.listen if explicit_listen else ([] if o.config_file else [DEFAULT_ROUTER])
        o.connect = getattr(args, "connect", None) or [e for e in os.environ.get("BALLBOT_CONNECT", "").split(",") if e]
    return o


# --- run / up ----------------------------------------------------------------------------------

def cmd_run(args: argparse.Namespace) -> int:
    from common.node import Node

    if args.service == "router":
        return run_router(zenoh_options(args, "router"), robot_id(args))
    m, settings_cls = service_module(args.service)
    settings = load_settings(settings_cls, config_file(args), args)
    # What can be known before the service is up (a missing optional dependency, a deployment
    # that lacks a setting) fails here, before it announces itself: `up` and a healthcheck never
    # see a service come up that could not run.
    if hasattr(m, "preflight"):
        m.preflight(settings)
    node_options = m.node_options(settings) if hasattr(m, "node_options") else {}
    # the camera on the robot: one section every service reads (common/settings.py MountSettings)
    mount = load_settings(MountSettings, config_file(args), args, prefix="mount-")
    with Node(args.service, zenoh_options(args), robot_id(args), instance=args.instance, mount=mount,
              **node_options) as node:
        m.run(node, settings)
    return 0


def run_router(o: ZenohOptions, rid: str) -> int:
    from common.node import Node

    with Node("router", o, rid) as node:
        log.info("zenoh router listening on %s", ", ".join(o.listen) or f"the endpoints of {o.config_file}")
        node.stop_event.wait()
    return 0


def up_endpoints(args: argparse.Namespace) -> tuple[list[str], str]:
    """-> (where `up`'s router listens, where its services connect). --listen sets the router's
    endpoints (e.g. tcp/0.0.0.0:7447 so offboard workers can reach it) and the services connect to
    the first of them on loopback; --connect alone is both, as before."""
    o = zenoh_options(args)
    explicit_listen = getattr(args, "listen", None) or [e for e in os.environ.get("BALLBOT_LISTEN", "").split(",") if e]
    explicit_connect = (getattr(args, "connect", None)
                        or [e for e in os.environ.get("BALLBOT_CONNECT", "").split(",") if e])
    if not explicit_listen:
        endpoint = o.connect[0] if o.connect else DEFAULT_ROUTER
        return [endpoint], endpoint
    for e in explicit_listen:
        if "/" not in e or e.split("/", 1)[1].rsplit(":", 1)[-1] in ("", "0"):
            raise BallbotError(f"--listen {e}: `up` needs a fixed port for its router (e.g. tcp/0.0.0.0:7447)")
    if explicit_connect:
        return list(explicit_listen), explicit_connect[0]
    proto, addr = explicit_listen[0].split("/", 1)
    host, _, port = addr.rpartition(":")
    if host.strip("[]") in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    return list(explicit_listen), f"{proto}/{host}:{port}"


def cmd_up(args: argparse.Namespace) -> int:
    from common.supervisor import Supervisor

    listen, endpoint = up_endpoints(args)
    common = ["--robot-id", robot_id(args)]
    if cfg := config_file(args):
        common += ["--config", cfg]
    if args.nice < 0 and os.geteuid() != 0:
        log.warning("up --nice %d needs root (or CAP_SYS_NICE); the services run at the default priority", args.nice)
    import secrets

    from common.signing import KEY_ENV, KEY_FILE_ENV, remove_run_key, write_run_key

    # The services of this run share a calibration key: rectify takes only calibrations signed with
    # it (capture's, from a ROS camera's CameraInfo or a recording; `calibration publish` by this
    # user, who finds it in the run's key file). A key given by the user (KEY_ENV, KEY_FILE_ENV) wins.
    env = dict(os.environ)
    own_key = None
    if not env.get(KEY_ENV) and not env.get(KEY_FILE_ENV):
        own_key = secrets.token_hex(32)
        env[KEY_ENV] = own_key
        key_path = write_run_key(robot_id(args), own_key)
    sup = Supervisor(stop_timeout_s=args.stop_timeout, nice=args.nice, env=env)
    sup.add("router", ["run", "router"] + [a for e in listen for a in ("--listen", e)] + common)
    services = PIPELINE + (["ros2"] if getattr(args, "ros2", False) else [])
    services += ["viewer"] if getattr(args, "viewer", False) else []
    services += ["foxglove"] if getattr(args, "foxglove", False) else []
    for name in services:
        sup.add(name, ["run", name, "--connect", endpoint] + common, nice_offset=stage_nice(name),
                optional=name not in PIPELINE)
    print(f"ballbot-vision: starting {', '.join(['router'] + services)}; router on {', '.join(listen)}", flush=True)
    print(f"ballbot-vision: obstacles are published on ballbot/obstacles/{robot_id(args)} "
          f"(watch them with: ballbot-vision watch --connect {endpoint})", flush=True)
    if own_key is not None:
        print(f"ballbot-vision: this run's calibration key is in {key_path} (readable by you only; "
              f"`ballbot-vision calibration publish CAL` signs with it)", flush=True)
    try:
        return sup.run(wait_for_endpoint=endpoint)
    finally:
        if own_key is not None:
            remove_run_key(robot_id(args), own_key)


# --- watch / status / schema -------------------------------------------------------------------

def cmd_watch(args: argparse.Namespace) -> int:
    from ballbot_vision.watch import watch

    return watch(zenoh_options(args), args.robot, args.json, args.count, args.timeout)


def cmd_status(args: argparse.Namespace) -> int:
    from ballbot_vision.status import status

    return status(zenoh_options(args), args.robot or "*", args.wait, args.json)


def cmd_healthcheck(args: argparse.Namespace) -> int:
    """Exit 0 once every service on this host (a container's own) reports healthy stats: published
    stats whose health is ok. A service that is up but makes no progress (input arrives and nothing
    is published, or every input fails) fails the check, with its reason on stderr.

    Only stats from a service's own key count, and only when the message names that service
    (status.stats_source): an offboard worker may write nothing but the workers' key, so it cannot
    make a robot service look healthy. `--worker` checks this host's disparity workers instead,
    from that key (what an offboard worker's container runs)."""
    import socket
    import threading
    import time

    from common import codec
    from common.errors import DecodeError
    from common.keys import topic
    from common.messages import ServiceStats
    from common.zenoh_session import open_session

    host = socket.gethostname()
    seen: dict[str, ServiceStats] = {}
    changed = threading.Condition()

    from ballbot_vision.status import as_worker, stats_source

    untrusted: list[str] = []

    def on_stats(sample) -> None:
        try:
            st = codec.decode(sample.payload.to_bytes(), ServiceStats)
        except DecodeError:
            return
        where = stats_source(str(sample.key_expr), st)
        if where is None or where[1] == args.worker:  # forged, or a key of the other kind
            if where is None or not args.worker:
                with changed:
                    untrusted.append(str(sample.key_expr))
            return
        st = st if where[1] else as_worker(st)
        if st.host == host and (args.service is None or st.service == args.service):
            with changed:
                seen[st.instance] = st
                changed.notify_all()

    def verdict() -> tuple[bool, list[str]]:
        bad = [f"{s.service} {s.instance}: {s.status}" for s in seen.values() if s.health in ("degraded", "failed")]
        return bool(seen) and not bad and all(s.health == "ok" for s in seen.values()), bad

    o = zenoh_options(args)
    if args.mode is None and not os.environ.get("BALLBOT_MODE"):
        o.mode = "client"
        o.listen = []
    deadline = time.monotonic() + args.timeout
    with open_session(o) as session:
        session.declare_subscriber(topic("worker_stats" if args.worker else "stats").pattern(robot_id(args)),
                                   on_stats)
        session.declare_subscriber(topic("pool_stats").pattern(), on_stats)  # a fleet pool's worker
        with changed:
            while True:
                ok, bad = verdict()
                left = deadline - time.monotonic()
                if ok or bad or left <= 0:
                    break
                changed.wait(left)
    if bad:
        print("unhealthy: " + "; ".join(bad), file=sys.stderr)
    elif not ok:
        what = "any disparity worker" if args.worker else (args.service or "any service")
        print(f"no healthy stats from {what} on host {host} within {args.timeout:g} s"
              + (f" (last: {', '.join(s.status for s in seen.values())})" if seen else "")
              + (f"; not trusted: {len(untrusted)} message(s) from workers' keys or that do not match their key"
                 if untrusted else ""), file=sys.stderr)
    return 0 if ok else 1


def cmd_schema(args: argparse.Namespace) -> int:
    from common.messages import PUBLIC_MODELS

    if args.model:
        if args.model not in PUBLIC_MODELS:
            raise BallbotError(f"unknown message {args.model!r}; known: {', '.join(PUBLIC_MODELS)}")
        doc = PUBLIC_MODELS[args.model].model_json_schema()
    else:
        doc = {name: m.model_json_schema() for name, m in PUBLIC_MODELS.items()}
    print(json.dumps(doc, indent=2))
    return 0


def cmd_keys(args: argparse.Namespace) -> int:
    from common.keys import TOPICS, markdown_table

    if args.markdown:
        print(markdown_table(), end="")
        return 0
    rid = robot_id(args)
    print(f"{'key':52} {'message':14} {'producer':14} {'rate':>6}  description")
    for t in TOPICS.values():
        print(f"{t.pattern(rid):52} {(t.model.__name__ if t.model else 'liveliness'):14} {t.producer:14} "
              f"{(str(t.rate_hz) + ' Hz') if t.rate_hz else 'event':>6}  {t.description}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from bench.command import bench_main

    return bench_main(args)


# --- parser ------------------------------------------------------------------------------------

BUILTIN_COMMANDS = ("up", "run", "watch", "status", "schema", "healthcheck", "keys", "bench", "viewer", "foxglove")
# Services a person starts by name beside a running pipeline: `ballbot-vision viewer` is `run viewer`.
SERVICE_COMMANDS = ("viewer", "foxglove")


def _wanted(argv: list[str] | None) -> tuple[str | None, str | None]:
    """(command, service of `run`) named on the command line, so that only their parsers are built
    and only their modules imported: `run router` and `healthcheck` start without OpenCV or any
    service. (None, None) when unclear (help, typos): then everything is built."""
    if argv is None:
        return None, None
    words: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a == "--log-level":
            skip = True
        elif not a.startswith("-"):
            words.append(a)
            if len(words) == 2:
                break
        elif not words and a in ("-h", "--help"):
            return None, None
    command = words[0] if words else None
    service = words[1] if command == "run" and len(words) > 1 else None
    return command, service


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The whole CLI; given the argv about to be parsed, only the parts it names are built fully
    (the others are bare names: enough for argparse to pick the command)."""
    wanted, wanted_service = _wanted(argv)

    def needed(name: str) -> bool:
        return wanted is None or wanted == name

    p = argparse.ArgumentParser(prog="ballbot-vision", description=__doc__)
    p.add_argument("--log-level", default=os.environ.get("BALLBOT_LOG", "INFO"), help="[BALLBOT_LOG]")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def common(sp: argparse.ArgumentParser) -> argparse.ArgumentParser:
        sp.add_argument("--robot-id", default=None, help="robot id in every key [BALLBOT_ROBOT_ID] (default: ballbot)")
        sp.add_argument("--config", default=None, metavar="FILE",
                        help="YAML file with one section per service [BALLBOT_CONFIG]")
        add_zenoh_arguments(sp)
        return sp

    def stub(name: str) -> None:
        sub.add_parser(name, add_help=False)

    def service_parser(subparsers, name: str) -> argparse.ArgumentParser:
        """A service's arguments (`run NAME`, and the top-level `viewer` and `foxglove`): its settings,
        the mount section, the Zenoh session."""
        m, settings_cls = service_module(name)
        sp = common(subparsers.add_parser(name, help=(m.__doc__ or "").strip().splitlines()[0]))
        sp.add_argument("--instance", default=None, help="instance name in stats and liveliness (default: host-pid)")
        add_settings_arguments(sp, settings_cls)
        add_settings_arguments(sp, MountSettings, prefix="mount-")
        return sp

    if needed("up"):
        up = common(sub.add_parser("up", help="start every service as a separate process; Ctrl-C stops all",
                                   description="--listen: where the router listens (e.g. tcp/0.0.0.0:7447 for "
                                               "offboard workers; the services connect to it on loopback); --connect: "
                                               "where the router listens and the services connect (default "
                                               "tcp/127.0.0.1:7447)"))
        up.add_argument("--stop-timeout", type=float, default=10.0, metavar="S",
                        help="seconds the services get to stop after SIGTERM before they are killed (default: 10)")
        up.add_argument("--nice", type=int, default=int(os.environ.get("BALLBOT_NICE", 0)), metavar="N",
                        help="scheduling priority of the services, -20..19 (negative: ahead of other work on the "
                             "robot, e.g. -5; needs root) [BALLBOT_NICE] (default: 0)")
        up.add_argument("--ros2", action="store_true", help="also start the ROS 2 bridge (`run ros2`: topics on "
                        "rmw_zenoh; settings in the config's ros2 section)")
        up.add_argument("--viewer", action="store_true", help="also start the web viewer (default "
                        "http://127.0.0.1:8080; settings in the config's viewer section or BALLBOT_VIEWER_*)")
        up.add_argument("--foxglove", action="store_true", help="also start the live Foxglove server (default "
                        "ws://127.0.0.1:8765; settings in the config's foxglove section or BALLBOT_FOXGLOVE_*)")
        up.set_defaults(func=cmd_up)
    else:
        stub("up")

    if needed("run"):
        run = sub.add_parser("run", help="start one service (what a container runs)")
        run_sub = run.add_subparsers(dest="service", required=True, metavar="SERVICE")
        r = common(run_sub.add_parser("router", help="a Zenoh router (a Python session in router mode)"))
        r.add_argument("--instance", default=None)
        r.set_defaults(func=cmd_run)
        for name in SERVICES:
            if wanted_service not in (None, name) and wanted_service in list(SERVICES) + ["router"]:
                run_sub.add_parser(name, add_help=False)
                continue
            service_parser(run_sub, name).set_defaults(func=cmd_run)
    else:
        stub("run")

    if needed("watch"):
        w = common(sub.add_parser("watch", help="print obstacle lists from ballbot/obstacles/**"))
        w.add_argument("--robot", default=None, help="only this robot (default: every robot)")
        w.add_argument("--json", action="store_true", help="one JSON object per obstacle list")
        w.add_argument("--count", type=int, default=0, help="exit after N lists (0: run until Ctrl-C)")
        w.add_argument("--timeout", type=float, default=0, help="exit with status 1 if nothing arrives in this many s")
        w.set_defaults(func=cmd_watch)
    else:
        stub("watch")

    if needed("status"):
        s = common(sub.add_parser("status", help="every live service instance: rate, latency, drops, errors"))
        s.add_argument("--robot", default=None, help="only this robot")
        s.add_argument("--wait", type=float, default=2.5, help="seconds to listen for stats")
        s.add_argument("--json", action="store_true")
        s.set_defaults(func=cmd_status)
    else:
        stub("status")

    if needed("schema"):
        sc = sub.add_parser("schema", help="JSON Schema of the public messages")
        sc.add_argument("model", nargs="?", default=None, help="one message (default: all)")
        sc.set_defaults(func=cmd_schema)
    else:
        stub("schema")

    if needed("healthcheck"):
        hc = common(sub.add_parser("healthcheck", help="exit 0 if the services on this host report progress "
                                                                "(containers)"))
        hc.add_argument("--service", default=None, help="only this service")
        hc.add_argument("--worker", action="store_true", help="check this host's disparity workers (their own, "
                        "self-reported stats key) instead of the robot's services")
        hc.add_argument("--timeout", type=float, default=3.0)
        hc.set_defaults(func=cmd_healthcheck)
    else:
        stub("healthcheck")

    if needed("keys"):
        k = sub.add_parser("keys", help="the Zenoh key table")
        k.add_argument("--robot-id", default=None)
        k.add_argument("--markdown", action="store_true", help="the table as Markdown (docs/keys.md)")
        k.set_defaults(func=cmd_keys)
    else:
        stub("keys")

    if needed("bench"):
        b = common(sub.add_parser("bench", help="throughput and latency, per stage and end to end"))
        from bench.command import add_bench_arguments

        add_bench_arguments(b)
        b.set_defaults(func=cmd_bench)
    else:
        stub("bench")

    for name in SERVICE_COMMANDS:
        if needed(name):
            service_parser(sub, name).set_defaults(func=cmd_run, service=name)
        else:
            stub(name)

    if wanted is None or wanted not in BUILTIN_COMMANDS:
        for module in COMMAND_MODULES:
            importlib.import_module(module).register(sub, common)
    return p


# the commands whose process is a service, or starts services that inherit its environment
SERVICE_PROCESS_COMMANDS = ("run", "up", *SERVICE_COMMANDS)
# OpenCV's pthreads pool (OpenCV's documented tuning variables): after each parallel call its
# threads spin for a while before they sleep. A service that runs one call a frame beside three
# other processes on two cores pays that spin on every frame: StereoBM with 2 threads costs
# 16-18 ms of CPU a pair instead of 19-21 ms when they sleep at once, at the same speed (bench).
OPENCV_POOL_SLEEPS = {"OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": "0", "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": "0"}


def quiet_opencv_pool() -> None:
    """Set before this process imports cv2 (OpenCV reads them once, when its library loads), and
    inherited by the services `up` starts; a value the user set wins."""
    for name, value in OPENCV_POOL_SLEEPS.items():
        os.environ.setdefault(name, value)


def main(argv: list[str] | None = None) -> int:
    from common.node import setup_logging

    argv = sys.argv[1:] if argv is None else list(argv)
    # OpenCV's own log lines ("[ WARN:0@0.1] global loadsave.cpp ...") repeat what our errors say
    # better; errors that matter reach the user as ours. OPENCV_LOG_LEVEL set by the user wins.
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    if _wanted(argv)[0] in SERVICE_PROCESS_COMMANDS:
        quiet_opencv_pool()
    args = build_parser(argv).parse_args(argv)
    setup_logging(args.log_level.upper())
    try:
        return args.func(args) or 0
    except BallbotError as e:
        print(f"ballbot-vision: error: {e}", file=sys.stderr)
        return e.exit_status
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `... | head` closed the pipe: not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:
        # A path the user gave that cannot be written (or made): -o into a missing or read-only
        # folder, a folder where a file goes. Input files are read through common/files.py, which
        # words its own errors; an OSError without a path is not the user's and keeps its traceback.
        if e.filename is None:
            raise
        from common.errors import path_error

        print(f"ballbot-vision: error: {e.filename}: {path_error(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
