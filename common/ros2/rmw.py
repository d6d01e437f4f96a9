"""What rmw_zenoh (ROS 2's Zenoh middleware, `rmw_zenoh_cpp`) puts on the wire, as pure functions:
ROS names, data keys, liveliness tokens, the QoS string, the per-sample attachment and the GID.
No Zenoh import here; graph.py declares these on a session.

From rmw_zenoh's sources (jazzy 0.2.x / humble 0.1.x; liveliness_utils.cpp, attachment_helpers.cpp,
qos.cpp, rmw_publisher_data.cpp):

data key          <domain_id>/<fully qualified topic name without the leading '/'>/<DDS type name>/<type hash>
                  e.g. 0/ballbot/obstacles/vision_msgs::msg::dds_::Detection3DArray_/RIHS01_793f...
liveliness token  @ros2_lv/<domain_id>/<session zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>
                  [/<topic name>/<DDS type name>/<type hash>/<qos>]   (every name with '/' written as '%')
                  kind: NN node (entity id = node id), MP publisher, MS subscription, SS service, SC client
attachment        int64 sequence number (from 1), int64 source timestamp (ns, system clock),
                  then the GID as a Zenoh-serialised byte sequence: LEB128 length + bytes; little endian
GID               XXH3-128 of the entity's liveliness token, low 64 bits then high 64 bits (little endian),
                  zero-padded to RMW_GID_STORAGE_SIZE (16 since Iron, 24 in Humble)

Humble versus Jazzy: Humble's rosidl has no type hashes, so rmw_zenoh's humble branch writes the
constant "TypeHashNotSupported" where Jazzy writes "RIHS01_<sha256 hex>", and Humble's GID storage
is 24 bytes. Everything else is the same.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Literal

ADMIN_SPACE = "@ros2_lv"
TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"


class RosNameError(ValueError):
    """A ROS name (topic, namespace, node) that ROS would refuse."""


@dataclass(frozen=True)
class Distro:
    name: str
    type_hashes: bool  # False: the key and tokens carry "TypeHashNotSupported"
    gid_size: int      # RMW_GID_STORAGE_SIZE of that distro's rmw


DISTROS: dict[str, Distro] = {
    "humble": Distro("humble", type_hashes=False, gid_size=24),
    "jazzy": Distro("jazzy", type_hashes=True, gid_size=16),
}


def distro(name: str) -> Distro:
    try:
        return DISTROS[name]
    except KeyError:
        raise ValueError(f"unknown ROS distro {name!r} (known: {', '.join(DISTROS)})") from None


# --- names --------------------------------------------------------------------------------------

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def _check_tokens(name: str, what: str) -> None:
    for tok in name.strip("/").split("/"):
        if not _TOKEN.match(tok) or "__" in tok:
            raise RosNameError(f"{what} {name!r}: {tok!r} is not a valid name token "
                               "(letters, digits and single underscores, not starting with a digit)")


def check_namespace(ns: str) -> str:
    """'/' or '/a/b' (a relative 'a/b' is made absolute); raises RosNameError."""
    ns = ns.strip() or "/"
    if not ns.startswith("/"):
        ns = "/" + ns
    if ns != "/":
        if ns.endswith("/"):
            raise RosNameError(f"namespace {ns!r} must not end with '/'")
        _check_tokens(ns, "namespace")
    return ns


def check_node_name(name: str) -> str:
    if "/" in name or not _TOKEN.match(name) or "__" in name:
        raise RosNameError(f"node name {name!r}: letters, digits and single underscores, not starting with a digit")
    return name


def resolve_topic(name: str, namespace: str = "/") -> str:
    """A topic name as ROS resolves it: absolute ('/tf_static') stays, relative ('obstacles') goes
    under the namespace. Returns the fully qualified name; raises RosNameError."""
    if not name or name.endswith("/") or "//" in name:
        raise RosNameError(f"topic name {name!r}: empty, trailing '/' or empty token")
    if name.startswith("~"):
        raise RosNameError(f"topic name {name!r}: private names (~) need a node; use a relative or absolute name")
    ns = check_namespace(namespace)
    fq = name if name.startswith("/") else (ns.rstrip("/") + "/" + name)
    _check_tokens(fq, "topic name")
    return fq


def mangle(name: str) -> str:
    """How rmw_zenoh writes a name inside a liveliness token: every '/' becomes '%'."""
    return name.replace("/", "%")


def dds_type_name(ros_type: str) -> str:
    """'sensor_msgs/msg/Image' -> 'sensor_msgs::msg::dds_::Image_' (what rosidl's typesupport reports)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"ROS type {ros_type!r}: expected package/msg/Name")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_from_dds(dds: str) -> str | None:
    """Inverse of dds_type_name; None for anything else."""
    m = re.fullmatch(r"([A-Za-z0-9_]+)::([A-Za-z0-9_]+)::dds_::([A-Za-z0-9_]+)_", dds)
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}" if m else None


# --- keys and tokens ----------------------------------------------------------------------------

def topic_key(domain_id: int, fq_topic: str, dds_type: str, type_hash: str) -> str:
    return f"{int(domain_id)}/{fq_topic.strip('/')}/{dds_type}/{type_hash}"


def topic_key_any_hash(domain_id: int, fq_topic: str, dds_type: str = "*") -> str:
    """Key expression for a subscriber that takes any type hash (Humble's or Jazzy's) and, with
    dds_type '*', any type."""
    return f"{int(domain_id)}/{fq_topic.strip('/')}/{dds_type}/*"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "/") -> str:
    return "/".join([ADMIN_SPACE, str(int(domain_id)), zid, str(node_id), str(node_id), "NN",
                     mangle(enclave), mangle(check_namespace(namespace)), mangle(check_node_name(node))])


def endpoint_token(kind: Literal["MP", "MS"], domain_id: int, zid: str, node_id: int, entity_id: int,
                   namespace: str, node: str, fq_topic: str, dds_type: str, type_hash: str, qos: str,
                   enclave: str = "/") -> str:
    return "/".join([ADMIN_SPACE, str(int(domain_id)), zid, str(node_id), str(entity_id), kind,
                     mangle(enclave), mangle(check_namespace(namespace)), mangle(check_node_name(node)),
                     mangle(fq_topic), mangle(dds_type), mangle(type_hash), qos])


# --- QoS ----------------------------------------------------------------------------------------

# rmw enum values (rmw/types.h)
RELIABILITY = {"reliable": 1, "best_effort": 2}
DURABILITY = {"transient_local": 1, "volatile": 2}
HISTORY = {"keep_last": 1, "keep_all": 2}
LIVELINESS_AUTOMATIC = 1
DURATION_INFINITE = (9223372036, 854775807)  # RMW_DURATION_INFINITE as (sec, nsec)


@dataclass(frozen=True)
class Qos:
    reliability: Literal["reliable", "best_effort"] = "reliable"
    durability: Literal["volatile", "transient_local"] = "volatile"
    history: Literal["keep_last", "keep_all"] = "keep_last"
    depth: int = 10

    def keyexpr(self) -> str:
        """The QoS chunk of a liveliness token. rmw_zenoh leaves a field empty when it equals its
        default (reliable, volatile, keep_last, depth 42, infinite deadline/lifespan/lease,
        automatic liveliness): '<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
        <liveliness>,<lease s>,<ns>'."""
        rel = "" if self.reliability == "reliable" else str(RELIABILITY[self.reliability])
        dur = "" if self.durability == "volatile" else str(DURABILITY[self.durability])
        hist = "" if self.history == "keep_last" else str(HISTORY[self.history])
        depth = "" if self.depth == 42 else str(int(self.depth))
        return f"{rel}:{dur}:{hist},{depth}:,:,:,,"


# --- attachment and GID -------------------------------------------------------------------------

_SEQ_TS = struct.Struct("<qq")


class AttachmentError(ValueError):
    pass


def gid(token: str, size: int) -> bytes:
    """The GID rmw_zenoh derives from an entity's liveliness token."""
    import xxhash

    h = xxhash.xxh3_128_intdigest(token.encode())
    return h.to_bytes(16, "little") + bytes(max(0, size - 16))


def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def encode_attachment(sequence_number: int, source_timestamp_ns: int, source_gid: bytes) -> bytes:
    return _SEQ_TS.pack(sequence_number, source_timestamp_ns) + _leb128(len(source_gid)) + bytes(source_gid)


def decode_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid); AttachmentError names what is wrong."""
    if len(raw) < _SEQ_TS.size + 1:
        raise AttachmentError(f"attachment of {len(raw)} bytes: shorter than sequence number + timestamp + gid length")
    seq, ts = _SEQ_TS.unpack_from(raw)
    n, shift, i = 0, 0, _SEQ_TS.size
    while True:
        if i >= len(raw) or shift > 28:
            raise AttachmentError("attachment: gid length is not a valid LEB128 number")
        b = raw[i]
        i += 1
        n |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            break
    if len(raw) != i + n:
        raise AttachmentError(f"attachment: gid of {n} bytes announced, {len(raw) - i} present")
    return seq, ts, bytes(raw[i:])
