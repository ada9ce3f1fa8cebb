"""Decode Foxglove messages with Foxglove's official schemas (the descriptors the foxglove-sdk
package ships), for the export test (tests/test_report.py) and the live view test (tests/test_live.py).

A channel of a Foxglove type (``foxglove.SceneUpdate``, ``foxglove.FrameTransforms``) carries
protobuf with a serialized ``FileDescriptorSet`` as its schema: :func:`check_official` asserts
that schema is byte for byte the SDK's own, :func:`decode` parses a message with it into a dict
(field names as in the .proto), failing on bytes that are not such a message.
"""

from __future__ import annotations

from typing import Any

from foxglove import messages as fm
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.json_format import MessageToDict

OFFICIAL = {"foxglove.SceneUpdate": fm.SceneUpdate, "foxglove.FrameTransforms": fm.FrameTransforms}

_classes: dict[tuple[str, bytes], Any] = {}


def check_official(name: str, encoding: str, data: bytes) -> None:
    """The schema ``name`` of a channel is Foxglove's official one, as the SDK ships it."""
    assert name in OFFICIAL, name
    official = OFFICIAL[name].get_schema()
    assert encoding == official.encoding == "protobuf", (name, encoding)
    assert bytes(data) == bytes(official.data), f"{name}: not the SDK's descriptor"


def decode(name: str, schema: bytes, data: bytes) -> dict[str, Any]:
    """Parse ``data`` as message ``name`` of the FileDescriptorSet ``schema``; a dict with every
    field (defaults included), or an exception."""
    cls = _classes.get((name, bytes(schema)))
    if cls is None:
        fds = descriptor_pb2.FileDescriptorSet.FromString(bytes(schema))
        pool = descriptor_pool.DescriptorPool()
        for fd in fds.file:
            pool.Add(fd)
        cls = _classes[(name, bytes(schema))] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
    msg = cls.FromString(bytes(data))
    assert msg.ByteSize() == len(data), f"{name}: bytes beyond the schema's fields"
    return MessageToDict(msg, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)
