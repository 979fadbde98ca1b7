"""Foxglove protobuf messages decoded with the descriptors their schemas carry (google.protobuf), as any
reader of the files would, without the classes that wrote them."""

from __future__ import annotations

import functools
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory


@functools.cache
def message_class(name: str, descriptors: bytes) -> Any:
    """The protobuf class of ``name`` built from a schema's FileDescriptorSet."""
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(descriptors).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def decoded(schema_name: str, descriptors: bytes, payload: bytes) -> Any:
    """``payload`` as a protobuf message of the schema ``schema_name`` (``foxglove.RawImage``, ...)."""
    return message_class(schema_name, bytes(descriptors)).FromString(payload)


def parsed(message: Any) -> Any:
    """A ``foxglove.messages`` object encoded, then decoded back through its own schema's descriptors."""
    schema = type(message).get_schema()
    return decoded(schema.name, bytes(schema.data), message.encode())
