"""The frame path between processes: decoding shares the payload's memory (no copy by pydantic or
numpy), and a frame arrives whole through Zenoh's shared memory (a peer on this host) and through
the network path (shared memory off, as for a peer on another host). Correctness only: what each
path costs is `ballbot-vision bench transport`."""
from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
from helpers import free_port

from common import codec
from common.errors import ConfigError
from common.inbox import Inbox, meta_of
from common.keys import topic
from common.messages import StereoFrame
from common.zenoh_session import ZenohOptions, make_config, open_session, options_from_args


def pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, (480, 640), np.uint8), rng.integers(0, 256, (480, 640), np.uint8)


def frame_payload(left: np.ndarray, right: np.ndarray, seq: int = 1) -> bytes:
    return codec.encode(StereoFrame(robot_id="t", seq=seq, stamp_ns=time.time_ns(), left=codec.image_from_array(left),
                                    right=codec.image_from_array(right), source="synthetic"))


def test_decoded_images_are_views_of_the_payload_bytes():
    left, right = pair()
    payload = frame_payload(left, right)
    doc = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    msg = StereoFrame.model_validate(doc)
    assert msg.left.data is doc["left"]["data"]  # validation keeps the bytes object msgpack made
    msg = codec.decode(payload, StereoFrame)
    a, b = codec.array_from_image(msg.left), codec.array_from_image(msg.right)
    assert np.array_equal(a, left) and np.array_equal(b, right)
    assert np.shares_memory(a, np.frombuffer(msg.left.data, np.uint8))  # a view, not a copy
    assert not a.flags.writeable  # so no stage can scribble on a buffer it shares


def test_shared_memory_is_on_by_default_and_can_be_turned_off(monkeypatch):
    import argparse

    conf = make_config(ZenohOptions())
    assert conf.get_json("transport/shared_memory/enabled") == "true"
    assert conf.get_json("transport/shared_memory/transport_optimization/enabled") == "true"
    monkeypatch.setenv("BALLBOT_SHM", "0")
    o = options_from_args(argparse.Namespace())
    assert o.shared_memory is False and o.for_router().shared_memory is False
    assert make_config(o).get_json("transport/shared_memory/enabled") == "false"
    monkeypatch.setenv("BALLBOT_SHM", "maybe")
    with pytest.raises(ConfigError, match="BALLBOT_SHM 'maybe'"):
        options_from_args(argparse.Namespace())


def test_a_config_file_decides_shared_memory_unless_told(tmp_path, monkeypatch):
    f = tmp_path / "z.json5"
    f.write_text('{ transport: { shared_memory: { enabled: false } } }')
    assert make_config(ZenohOptions(config_file=str(f))).get_json("transport/shared_memory/enabled") == "false"
    assert make_config(ZenohOptions(config_file=str(f), shared_memory=True)).get_json(
        "transport/shared_memory/enabled") == "true"


def test_a_frame_arrives_whole_through_shared_memory_and_through_the_network_path():
    """One publisher, two subscribers: one with shared memory (a peer on this host), one without
    (what a peer on another host gets: the bytes over TCP). Both hand on the same arrays."""
    import zenoh

    left, right = pair()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    key = "test/transport/frames"
    with open_session(ZenohOptions(mode="peer", connect=[], listen=[endpoint], lease_ms=None)) as pub_s, \
            open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=[], lease_ms=None)) as shm_s, \
            open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=[], lease_ms=None,
                                      shared_memory=False)) as net_s:
        inboxes = {"shm": Inbox(topic("frames_rect")), "network": Inbox(topic("frames_rect"))}
        arrived = {name: threading.Event() for name in inboxes}

        def callback(name):
            def on_sample(sample) -> None:
                inboxes[name].offer_sample(sample)
                arrived[name].set()
            return on_sample

        shm_s.declare_subscriber(key, callback("shm"))
        net_s.declare_subscriber(key, callback("network"))
        pub = pub_s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 60
        seq = 0
        # the subscribers' interest reaches the publisher after a moment, and Zenoh sets its shared
        # memory up lazily (the first payloads go by the link): put until both have one, the first
        # through shared memory
        while (not all(e.is_set() for e in arrived.values()) or not inboxes["shm"].shm) and time.monotonic() < deadline:
            seq += 1
            pub.put(frame_payload(left, right, seq))
            for e in arrived.values():
                e.wait(0.2)
        assert all(e.is_set() for e in arrived.values()), {n: e.is_set() for n, e in arrived.items()}
        for name, inbox in inboxes.items():
            payload = inbox.take(1.0)
            msg = codec.decode(payload, StereoFrame)
            assert np.array_equal(codec.array_from_image(msg.left), left), name
            assert np.array_equal(codec.array_from_image(msg.right), right), name
        assert inboxes["shm"].shm >= 1
        assert inboxes["network"].shm == 0 and inboxes["network"].received >= 1


def test_meta_of_ignores_a_missing_attachment():
    assert meta_of(None) is None


def test_live_tokens_sees_the_tokens_alive_before_it_and_their_coming_and_going():
    """`status`'s view of who is alive (common/zenoh_session.py: LiveTokens), as `up` lays the
    sessions out: peers that listen and meet through a router's gossip, and a newcomer. A liveliness
    query from the newcomer in its first seconds can come back empty (the flake LiveTokens answers):
    the subscriber's history must hold every token from the start."""
    from common.zenoh_session import LiveTokens

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    peer = ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"], lease_ms=None)
    with open_session(ZenohOptions(mode="router", connect=[], listen=[endpoint], lease_ms=None)), \
            open_session(peer) as a, open_session(peer) as b:
        token_a = a.liveliness().declare_token("test/alive/a")  # noqa: F841 (a dropped token is undeclared)
        token_b = b.liveliness().declare_token("test/alive/b")
        deadline = time.monotonic() + 30

        def wait_for(tokens: LiveTokens, want: set[str]) -> None:
            while tokens.keys() != want and time.monotonic() < deadline:
                time.sleep(0.05)
            assert tokens.keys() == want

        with open_session(peer) as newcomer:
            tokens = LiveTokens(newcomer, "test/alive/*")
            wait_for(tokens, {"test/alive/a", "test/alive/b"})
            token_b.undeclare()
            wait_for(tokens, {"test/alive/a"})
            c = a.liveliness().declare_token("test/alive/c")
            wait_for(tokens, {"test/alive/a", "test/alive/c"})
            c.undeclare()
