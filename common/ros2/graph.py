"""The thin Zenoh shell of a ROS 2 participant as rmw_zenoh would be: a node (its NN liveliness
token), publishers (advanced publisher on the data key + MP token + attachment per sample) and
subscriptions (subscriber on the data key with any type hash + MS token). The formats are rmw.py's.

Like rmw_zenoh: one counter per session numbers the node and then its entities; a publisher is a
Zenoh AdvancedPublisher, congestion control DROP (BLOCK for reliable keep-all), reliability from
the QoS; transient-local publishers keep `depth` samples in a cache that late transient-local
subscribers (tf2's static listener) query, detect-able through liveliness, with sporadic
heartbeats when reliable. Sequence numbers start at 1.
"""
from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from typing import Any

from common.ros2 import rmw
from common.ros2.msgs import RosTypes


class RosNode:
    def __init__(self, session: Any, types: RosTypes, domain_id: int, namespace: str, name: str,
                 enclave: str = "/"):
        self.session, self.types = session, types
        self.domain_id = int(domain_id)
        self.namespace = rmw.check_namespace(namespace)
        self.name = rmw.check_node_name(name)
        self.enclave = enclave
        self.zid = str(session.info.zid())
        self._ids = itertools.count()
        self.node_id = next(self._ids)
        self.token_key = rmw.node_token(self.domain_id, self.zid, self.node_id, self.namespace, self.name, enclave)
        self._token = session.liveliness().declare_token(self.token_key)
        self.entities: list[Any] = []

    def publisher(self, topic: str, typename: str, qos: rmw.Qos) -> RosPublisher:
        p = RosPublisher(self, topic, typename, qos)
        self.entities.append(p)
        return p

    def subscription(self, topic: str, typename: str, qos: rmw.Qos,
                     callback: Callable[[str, bytes, bytes | None], None], any_type: bool = False) -> RosSubscription:
        s = RosSubscription(self, topic, typename, qos, callback, any_type)
        self.entities.append(s)
        return s

    def close(self) -> None:
        for e in self.entities:
            e.close()
        self._undeclare(self._token)

    @staticmethod
    def _undeclare(obj: Any) -> None:
        try:
            obj.undeclare()
        except Exception:  # the session is closing already
            pass


class RosPublisher:
    def __init__(self, node: RosNode, topic: str, typename: str, qos: rmw.Qos):
        import zenoh
        import zenoh.ext

        t = node.types
        self.node, self.typename, self.qos = node, typename, qos
        self.topic = rmw.resolve_topic(topic, node.namespace)
        self.entity_id = next(node._ids)
        self.type_hash = t.type_hash(typename)
        dds = t.dds_type(typename)
        self.key = rmw.topic_key(node.domain_id, self.topic, dds, self.type_hash)
        self.token_key = rmw.endpoint_token("MP", node.domain_id, node.zid, node.node_id, self.entity_id,
                                            node.namespace, node.name, self.topic, dds, self.type_hash,
                                            qos.keyexpr(), node.enclave)
        self.gid = rmw.gid(self.token_key, t.distro.gid_size)
        reliable = qos.reliability == "reliable"
        kwargs: dict[str, Any] = dict(
            congestion_control=zenoh.CongestionControl.BLOCK if reliable and qos.history == "keep_all"
            else zenoh.CongestionControl.DROP,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT)
        if qos.durability == "transient_local":
            kwargs.update(publisher_detection=True, cache=zenoh.ext.CacheConfig(max_samples=max(1, qos.depth)))
            if reliable:
                kwargs["sample_miss_detection"] = zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5)
        self._pub = zenoh.ext.declare_advanced_publisher(node.session, self.key, **kwargs)
        self._token = node.session.liveliness().declare_token(self.token_key)
        self._lock = threading.Lock()
        self.sequence_number = 1
        self.published = 0
        self.bytes = 0

    def publish(self, msg: Any) -> int:
        """Serialise (CDR) and put with the rmw attachment; returns the payload size."""
        payload = self.node.types.serialize(msg)
        with self._lock:
            att = rmw.encode_attachment(self.sequence_number, time.time_ns(), self.gid)
            self.sequence_number += 1
            self._pub.put(payload, attachment=att)
            self.published += 1
            self.bytes += len(payload)
        return len(payload)

    def close(self) -> None:
        RosNode._undeclare(self._token)
        RosNode._undeclare(self._pub)


class RosSubscription:
    """Subscribes to a ROS topic published by any rmw_zenoh participant, of any distro (the type
    hash chunk is a wildcard; with any_type also the type chunk). callback(key, payload,
    attachment) runs on Zenoh's thread: keep it short."""

    def __init__(self, node: RosNode, topic: str, typename: str, qos: rmw.Qos,
                 callback: Callable[[str, bytes, bytes | None], None], any_type: bool = False):
        t = node.types
        self.node, self.typename = node, typename
        self.topic = rmw.resolve_topic(topic, node.namespace)
        self.entity_id = next(node._ids)
        dds = t.dds_type(typename)
        self.key = rmw.topic_key_any_hash(node.domain_id, self.topic, "*" if any_type else dds)
        self.token_key = rmw.endpoint_token("MS", node.domain_id, node.zid, node.node_id, self.entity_id,
                                            node.namespace, node.name, self.topic, dds, t.type_hash(typename),
                                            qos.keyexpr(), node.enclave)

        def on_sample(sample: Any) -> None:
            att = sample.attachment
            callback(str(sample.key_expr), sample.payload.to_bytes(), att.to_bytes() if att is not None else None)

        self._sub = node.session.declare_subscriber(self.key, on_sample)
        self._token = node.session.liveliness().declare_token(self.token_key)

    def close(self) -> None:
        RosNode._undeclare(self._token)
        RosNode._undeclare(self._sub)
