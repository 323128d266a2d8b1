"""How ROS 2 over Zenoh names things: data keys, liveliness tokens, the sample attachment.

Three flavours, chosen by ``ros2.mode`` (facts from ros2/rmw_zenoh docs/design.md and
rmw_zenoh_cpp/src/detail/liveliness_utils.cpp, attachment_helpers.cpp; zenoh-plugin-ros2dds):

- ``rmw_zenoh`` (Jazzy and later): data key ``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<RIHS01
  hash>``; every sample carries a 33-byte attachment (sequence number int64 LE, source time ns
  int64 LE, the length byte 16, the 16-byte publisher gid) without which rmw_zenoh's subscriber
  drops it; the graph is discovered through liveliness tokens
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP|MS>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``
  with ``/`` in names replaced by ``%``.
- ``humble``: the same with ``TypeHashNotSupported`` in the hash slots (rmw_zenoh on Humble
  keeps the 16-byte gid and 33-byte attachment: projects that talk to Humble's rmw_zenoh_cpp,
  e.g. nano-ros, send exactly that).
- ``bridge`` (zenoh-bridge-ros2dds / zenoh-plugin-ros2dds): plain topic keys (``scan``, under the
  bridge's namespace prefix if it has one), CDR payload, no attachment, no tokens.
"""

from __future__ import annotations

import hashlib
import struct
from typing import Literal

from racecav.services.ros2.msgs import HASH_UNSUPPORTED, dds_type, type_hash

Mode = Literal["rmw_zenoh", "humble", "bridge"]
ADMIN_SPACE = "@ros2_lv"
QOS_DEFAULT = "1:2:1,10:,:,:,,"
"""Token QoS: reliable : volatile : keep_last,10 : deadline : lifespan : liveliness (the last
three at their defaults). Written out in full so it parses whatever the reader's defaults."""

GID_SIZE = {"rmw_zenoh": 16, "humble": 16, "bridge": 0}


def mangle(name: str) -> str:
    """rmw_zenoh's mangling of names inside a token: every '/' becomes '%'."""
    return name.replace("/", "%")


def attachment(seq: int, source_time_ns: int, gid: bytes) -> bytes:
    """The rmw_zenoh sample attachment (zenoh-ext serialisation of int64, int64, uint8 array):
    sequence number and source time as little-endian int64, then the gid length as a one-byte
    LEB128 and the gid."""
    return struct.pack("<qqB", seq, source_time_ns, len(gid)) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time ns, gid) of an attachment; ValueError if malformed."""
    if len(data) < 17 or len(data) != 17 + data[16]:
        raise ValueError(f"attachment of {len(data)} bytes is not int64, int64, gid")
    seq, ts, n = struct.unpack_from("<qqB", data)
    return seq, ts, bytes(data[17:17 + n])


class Graph:
    """Keys and tokens of one ROS node as seen by rmw_zenoh or the DDS bridge.

    :param mode: rmw_zenoh | humble | bridge.
    :param domain_id: ROS_DOMAIN_ID.
    :param zid: the Zenoh session id of the ROS-side session (tokens name it).
    :param node: ROS node name.
    :param namespace: ROS namespace ("" or "/" for none).
    :param bridge_prefix: bridge mode: the bridge's namespace (key prefix), "" for none.
    :param node_id: the node's id within the session (rmw counts nodes per context).
    """

    def __init__(self, mode: Mode, domain_id: int, zid: str, node: str, namespace: str = "",
                 bridge_prefix: str = "", node_id: int = 0):
        self.mode, self.domain_id, self.zid, self.node = mode, domain_id, zid, node
        self.namespace = "/" + namespace.strip("/") if namespace.strip("/") else "/"
        self.bridge_prefix = bridge_prefix.strip("/")
        self.node_id = node_id
        self._next_eid = node_id + 1

    def topic_name(self, topic: str) -> str:
        """Fully qualified topic: absolute names stay, relative ones go under the namespace."""
        if topic.startswith("/"):
            return "/" + topic.strip("/")
        return self.namespace.rstrip("/") + "/" + topic.strip("/")

    def hash_of(self, type_name: str) -> str:
        return HASH_UNSUPPORTED if self.mode == "humble" else type_hash(type_name)

    def data_key(self, topic: str, type_name: str) -> str:
        """Zenoh key the samples of ``topic`` travel on."""
        name = self.topic_name(topic).strip("/")
        if self.mode == "bridge":
            return f"{self.bridge_prefix}/{name}" if self.bridge_prefix else name
        return f"{self.domain_id}/{name}/{dds_type(type_name)}/{self.hash_of(type_name)}"

    def _prefix(self, eid: int, kind: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{eid}/{kind}/"
                f"{mangle('/')}/{mangle(self.namespace)}/{mangle(self.node)}")

    def node_token(self) -> str | None:
        """The node's NN token (None in bridge mode: the bridge announces ROS entities itself)."""
        if self.mode == "bridge":
            return None
        return self._prefix(self.node_id, "NN")

    def entity_token(self, kind: Literal["MP", "MS"], topic: str, type_name: str,
                     qos: str = QOS_DEFAULT) -> tuple[str | None, bytes]:
        """(liveliness token, gid) of a new publisher (MP) or subscription (MS) of this node.

        The gid is derived from the token like rmw_zenoh does (a hash of the token text; here
        SHA-256 instead of XXH3, the value only has to be unique and stable)."""
        eid = self._next_eid
        self._next_eid += 1
        if self.mode == "bridge":
            return None, b""
        token = (f"{self._prefix(eid, kind)}/{mangle(self.topic_name(topic))}/"
                 f"{mangle(dds_type(type_name))}/{mangle(self.hash_of(type_name))}/{qos}")
        gid = hashlib.sha256(token.encode()).digest()[:GID_SIZE[self.mode]]
        gid += bytes(GID_SIZE[self.mode] - len(gid))
        return token, gid
