"""JSON Schema of every message as it travels (MCAP channels attach these).

For a JSON message the schema describes the payload object; for a frame message it
describes the JSON header inside the frame, where each array field is a descriptor
``{"dtype", "shape", "offset"}`` of raw bytes that follow (see ``protocol.codec``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from protocol.codec import is_frame
from protocol.message import Message, message_types


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of ``cls``'s payload, with ``schema`` and ``version`` consts."""
    body = cls.model_json_schema(mode="serialization")
    body["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    body["$id"] = f"artrack:{cls.SCHEMA}/{cls.VERSION}"
    body["title"] = cls.SCHEMA
    body["properties"] = {
        "schema": {"const": cls.SCHEMA},
        "version": {"const": cls.VERSION},
        **body["properties"],
    }
    body["required"] = ["schema", "version", *body.get("required", [])]
    body["x-artrack-layout"] = "frame" if is_frame(cls) else "json"
    return body


def write_schemas(folder: Path) -> list[Path]:
    """Write ``<schema name>.json`` for every registered message into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, cls in sorted(message_types().items()):
        path = folder / f"{name}.json"
        path.write_text(json.dumps(json_schema(cls), indent=2) + "\n")
        written.append(path)
    return written
