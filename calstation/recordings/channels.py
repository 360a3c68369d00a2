"""The layout of a version-2 recording: its channels, their schemas, and the reserved names.

``docs/recording-format.md`` describes each channel; :mod:`calstation.recordings.writer` writes
them and :mod:`calstation.recordings.reader` reads them (and the version-1 layout,
:mod:`calstation.recordings.v1`). The live view advertises the same channels.
"""

from __future__ import annotations

import json

from calstation.drivers import TurntableState
from calstation.jsonvalue import JSONObject
from calstation.recordings import messages as pb

FORMAT_VERSION: int = 2
"""Version of the recording layout (channels, schemas, metadata) described in the docs."""

SCAN_TOPIC = "/lidar/scan"
LIDAR_TOPIC = "/lidar/line"
ENCODER_TOPIC = "/encoder/count"
PLATTER_TF_TOPIC = "/tf"
STATIC_TF_TOPIC = "/tf_static"
CLOUD_TOPIC = "/platter/cloud"
TURNTABLE_TOPIC = "/turntable/status"
RECIPE_ATTACHMENT = "recipe.yaml"
"""The attachment that holds the text of the recipe a scan was taken with."""
RESERVED_METADATA = ("calstation", "lidar", "encoder", "calibration")
"""Metadata records the writer writes itself (no caller may add them)."""

TURNTABLE_SCHEMA: JSONObject = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "calstation.TurntableStatus",
    "description": "A status report of the turntable drive.",
    "type": "object",
    "properties": {
        "timestamp_ns": {"type": "integer", "description": "host-clock time, ns"},
        "state": {"type": "string", "enum": [s.value for s in TurntableState]},
        "speed_rpm": {"type": "number", "description": "signed speed, rpm"},
        "position_rad": {"type": ["number", "null"], "description": "position, rad, if known"},
        "faults": {"type": "array", "items": {"type": "string"}},
    },
    "required": ["timestamp_ns", "state", "speed_rpm"],
}
"""The JSON schema of the ``/turntable/status`` messages."""
_TURNTABLE = pb.SchemaData(
    "calstation.TurntableStatus", "jsonschema", json.dumps(TURNTABLE_SCHEMA).encode("utf-8")
)

CHANNELS: dict[str, tuple[str, str]] = {
    SCAN_TOPIC: ("foxglove.LaserScan", "protobuf"),
    LIDAR_TOPIC: (pb.LINE_TIMING_SCHEMA, "protobuf"),
    ENCODER_TOPIC: (pb.ENCODER_SCHEMA, "protobuf"),
    PLATTER_TF_TOPIC: ("foxglove.FrameTransform", "protobuf"),
    STATIC_TF_TOPIC: ("foxglove.FrameTransform", "protobuf"),
    CLOUD_TOPIC: ("foxglove.PointCloud", "protobuf"),
    TURNTABLE_TOPIC: ("calstation.TurntableStatus", "json"),
}
"""Topic → (schema name, message encoding) of a version-2 recording."""


def channel_schema(topic: str) -> pb.SchemaData:
    """The schema of a version-2 ``topic``."""
    name = CHANNELS[topic][0]
    return _TURNTABLE if name == _TURNTABLE.name else pb.schema(name)
