"""One place that turns `--mode/--connect/--listen/--zenoh-config` (or their BALLBOT_* environment
variables) into a Zenoh config.

Defaults suit one machine: peer mode, multicast scouting off (Docker and many Wi-Fi networks drop
multicast), listen on a free loopback port, connect to the local router that `ballbot-vision up`
starts on tcp/127.0.0.1:7447. Peers learn of each other through the router (gossip) and then talk
directly.

Shared memory: between peers on one host, Zenoh moves every payload above 3 KB (images, maps)
through a shared-memory pool and sends only a reference over the link; a peer on another host (or
one that cannot map the pool, e.g. a container without the host's /dev/shm) gets the bytes over
the network, with no change to publisher or subscriber. Measured with 614 KB payloads (a 640x480
pair) at 60/s: 0.45 ms of CPU per message at the publisher and 0.37 at the subscriber, against 0.81
and 0.64 without it. It is on unless BALLBOT_SHM=0 (or a --zenoh-config file turns it off).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
MAX_MESSAGE_BYTES = 128 << 20
DATA_QUEUE_BATCHES = 16  # per link, of 64 KB: the image streams' priority (see make_config)


@dataclass
class ZenohOptions:
    mode: str = "peer"
    connect: list[str] = field(default_factory=lambda: [DEFAULT_ROUTER])
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    config_file: str | None = None
    lease_ms: int | None = 2000  # a frozen or cut-off peer is dropped after this (Zenoh's default: 10 s)
    shared_memory: bool | None = None  # same-host payloads through shared memory; None: on, or as the config file says

    def for_router(self) -> ZenohOptions:
        """The same options for the router that `up` starts: it listens where the others connect."""
        return ZenohOptions(mode="router", connect=[], listen=list(self.connect) or [DEFAULT_ROUTER],
                            config_file=self.config_file, lease_ms=self.lease_ms, shared_memory=self.shared_memory)


def _split(v: str | None) -> list[str]:
    return [s.strip() for s in (v or "").split(",") if s.strip()]


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh (each also read from the environment variable shown)")
    g.add_argument("--mode", choices=["peer", "client", "router"], default=os.environ.get("BALLBOT_MODE"),
                   help="Zenoh session mode [BALLBOT_MODE] (default: peer)")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to connect to, repeatable [BALLBOT_CONNECT, comma separated] "
                   f"(default: {DEFAULT_ROUTER})")
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
    o.shared_memory = shared_memory_from_env()
    return o


def shared_memory_from_env() -> bool | None:
    """BALLBOT_SHM: 1/true/on or 0/false/off; unset: None (on, unless a config file says otherwise)."""
    from common.errors import ConfigError

    v = os.environ.get("BALLBOT_SHM", "").strip().lower()
    if not v:
        return None
    if v in ("1", "true", "on", "yes"):
        return True
    if v in ("0", "false", "off", "no"):
        return False
    raise ConfigError(f"BALLBOT_SHM {v!r}: 1 or 0 (on or off)")


def _zenoh_says(e: Exception) -> str:
    """A Zenoh error's own words, without the Rust source location and JSON5 wrapping."""
    text = str(e)
    m = re.search(r'msg: "(.*?)(?: at /[^"]*)?"', text)
    text = m.group(1) if m else text
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", text)
    parse = re.search(r"-->\s*(\d+):(\d+).*?=\s*([^\n]+)", text, re.S)  # JSON5's pointer at the error
    if parse:
        text = f"line {parse.group(1)}, column {parse.group(2)}: {parse.group(3)}"
    return " ".join(text.split()).rstrip(".!").strip()


def make_config(o: ZenohOptions):
    """The Zenoh config; a config file or endpoint Zenoh refuses is a ConfigError naming it."""
    import zenoh

    from common.errors import ConfigError

    if o.config_file:
        if not os.path.isfile(o.config_file):
            what = "is a folder, not a file" if os.path.exists(o.config_file) else "no such file or folder"
            raise ConfigError(f"--zenoh-config {o.config_file}: {what}")
        try:
            conf = zenoh.Config.from_file(o.config_file)
        except zenoh.ZError as e:
            raise ConfigError(f"--zenoh-config {o.config_file}: not a Zenoh config ({_zenoh_says(e)})") from None
    else:
        conf = zenoh.Config()
    # (what the user set, Zenoh's key, value): an error names the first
    settings = [(f"--mode {o.mode}", "mode", json.dumps(o.mode)), ("", "scouting/multicast/enabled", "false")]
    if o.connect:
        settings.append((f"--connect {','.join(o.connect)}", "connect/endpoints", json.dumps(o.connect)))
    if o.listen:
        settings.append((f"--listen {','.join(o.listen)}", "listen/endpoints", json.dumps(o.listen)))
    if o.lease_ms:
        settings.append((f"BALLBOT_LEASE_MS {o.lease_ms}", "transport/link/tx/lease", str(int(o.lease_ms))))
    shm = o.shared_memory if o.shared_memory is not None else (None if o.config_file else True)
    if shm is not None:  # said explicitly, so a change of Zenoh's default cannot turn it off unnoticed
        flag = "true" if shm else "false"
        settings.append((f"BALLBOT_SHM {int(shm)}", "transport/shared_memory/enabled", flag))
        settings.append((f"BALLBOT_SHM {int(shm)}", "transport/shared_memory/transport_optimization/enabled", flag))
    # Zenoh reassembles a fragmented message of up to 1 GB by default before anyone can look at
    # it; no message of ours comes near 128 MB (the per-key caps in keys.py are tighter still).
    settings.append(("", "transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES)))
    # A slow subscriber (a peer whose callback takes 1 s) keeps its link's DATA queue full; each time
    # it drains a batch, the publisher's next fragmented image waits there for up to Zenoh's fragment
    # deadline, and under CPU load healthy subscribers of the same put then lost frames too: with
    # 2 batches (128 KB) per priority, 3-50 of ~480 1.8 MB frames per 20 s on a loaded 2-core
    # machine; with 16 (1 MB, allocated lazily, Zenoh's maximum) 0-6, and the publisher waited 21-25 %
    # of the time instead of 28-39 % (issue 25, tests/test_reliability.py measures it in the pipeline).
    settings.append(("", "transport/link/tx/queue/size/data", str(DATA_QUEUE_BATCHES)))
    for option, key, value in settings:
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as e:
            raise ConfigError(f"{option or key + ' ' + value}: {_zenoh_says(e)}") from None
    return conf


def open_session(o: ZenohOptions) -> zenoh.Session:
    """Open a session; use as a context manager so callback threads stop on exit. A router that
    does not answer, or an endpoint that cannot be listened on, is a ConnectError (exit status 1:
    it may work a moment later, so `up` restarts a service that meets it)."""
    import zenoh

    from common.errors import ConnectError

    zenoh.try_init_log_from_env()
    conf = make_config(o)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        why = _zenoh_says(e)
        if why.startswith("Unable to connect"):
            where = ", ".join(o.connect) or "the endpoints of " + str(o.config_file)
            raise ConnectError(f"no Zenoh router answers at {where} (is it running, and --connect right?)") from None
        raise ConnectError(f"Zenoh session ({o.mode}): {why}") from None


class LiveTokens:
    """The liveliness tokens alive under a key expression, kept from a liveliness subscriber with
    history (the tokens alive when it is declared, then every appearance and disappearance).

    Why not a liveliness query: from a peer among peers that met through a router's gossip (as
    `up` lays them out), a query sometimes completes at once with no reply at all (about 1 in 5
    queries in a session's first 2 s, with eclipse-zenoh 1.10). `status` then called every service
    "stopped (liveliness token gone)" while all of them ran. The subscriber's history arrived complete
    in every run."""

    def __init__(self, session: zenoh.Session, key_expr: str):
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._sub = session.liveliness().declare_subscriber(key_expr, self._on_token, history=True)

    def _on_token(self, sample) -> None:
        import zenoh

        key = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._alive.discard(key)
            else:
                self._alive.add(key)

    def keys(self) -> set[str]:
        with self._lock:
            return set(self._alive)
