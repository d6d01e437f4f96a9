"""One place that turns `--mode/--connect/--listen/--zenoh-config` (or their BALLBOT_* environment
variables) into a Zenoh config.

Defaults suit one machine: peer mode, multicast scouting off (Docker and many Wi-Fi networks drop
multicast), listen on a free loopback port, connect to the local router that `ballbot-vision up`
starts on tcp/127.0.0.1:7447. Peers learn of each other through the router (gossip) and then talk
directly.
"""
from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass, field

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
MAX_MESSAGE_BYTES = 128 << 20


@dataclass
class ZenohOptions:
    mode: str = "peer"
    connect: list[str] = field(default_factory=lambda: [DEFAULT_ROUTER])
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    config_file: str | None = None
    lease_ms: int | None = 2000  # a frozen or cut-off peer is dropped after this (Zenoh's default: 10 s)

    def for_router(self) -> "ZenohOptions":
        """The same options for the router that `up` starts: it listens where the others connect."""
        return ZenohOptions(mode="router", connect=[], listen=list(self.connect) or [DEFAULT_ROUTER],
                            config_file=self.config_file, lease_ms=self.lease_ms)


def _split(v: str | None) -> list[str]:
    return [s.strip() for s in (v or "").split(",") if s.strip()]


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh (each also read from the environment variable shown)")
    g.add_argument("--mode", choices=["peer", "client", "router"], default=os.environ.get("BALLBOT_MODE"),
                   help="Zenoh session mode [BALLBOT_MODE] (default: peer)")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to, repeatable [BALLBOT_CONNECT, comma separated] (default: {DEFAULT_ROUTER})")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on, repeatable [BALLBOT_LISTEN] (default: tcp/127.0.0.1:0)")
    g.add_argument("--zenoh-config", default=os.environ.get("BALLBOT_ZENOH_CONFIG"), metavar="FILE",
                   help="a Zenoh JSON5 config file; the options above override it [BALLBOT_ZENOH_CONFIG]")


def options_from_args(args: argparse.Namespace) -> ZenohOptions:
    o = ZenohOptions()
    if getattr(args, "mode", None):
        o.mode = args.mode
    connect = getattr(args, "connect", None) or _split(os.environ.get("BALLBOT_CONNECT"))
    if connect:
        o.connect = connect
    listen = getattr(args, "listen", None) or _split(os.environ.get("BALLBOT_LISTEN"))
    if listen:
        o.listen = listen
    elif o.mode == "client":
        o.listen = []
    o.config_file = getattr(args, "zenoh_config", None)
    lease = os.environ.get("BALLBOT_LEASE_MS")
    if lease:
        o.lease_ms = int(lease)
    return o


def make_config(o: ZenohOptions):
    import zenoh

    conf = zenoh.Config.from_file(o.config_file) if o.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(o.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if o.connect:
        conf.insert_json5("connect/endpoints", json.dumps(o.connect))
    if o.listen:
        conf.insert_json5("listen/endpoints", json.dumps(o.listen))
    if o.lease_ms:
        conf.insert_json5("transport/link/tx/lease", str(int(o.lease_ms)))
    # Zenoh reassembles a fragmented message of up to 1 GB by default before anyone can look at
    # it; no message of ours comes near 128 MB (the per-key caps in keys.py are tighter still).
    conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    return conf


def open_session(o: ZenohOptions):
    """Open a session; use as a context manager so callback threads stop on exit."""
    import zenoh

    zenoh.try_init_log_from_env()
    return zenoh.open(make_config(o))
