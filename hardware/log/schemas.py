"""The schemas of a log's channels: JSON Schemas of the walker messages and of the companion
channels, and the Foxglove protobuf schemas (see the package docstring for the fields)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from typing import Any

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan as PbLaserScan
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap_protobuf.schema import build_file_descriptor_set


@dataclass(frozen=True)
class ChannelSchema:
    """A channel's schema as the log stores it."""

    name: str
    encoding: str  # MCAP schema encoding
    message_encoding: str  # MCAP channel message encoding
    data: bytes = field(repr=False)


def json_schema(name: str, doc: str, props: dict[str, dict[str, Any]]) -> ChannelSchema:
    """A JSON message whose fields are all required."""
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": name,
        "description": doc + ' Non-finite numbers are the strings "NaN", "Infinity", "-Infinity".',
        "type": "object",
        "properties": props,
        "required": list(props),
    }
    return ChannelSchema(name, "jsonschema", "json", json.dumps(schema, indent=1).encode())


def prop(json_type: str, description: str, **extra: Any) -> dict[str, Any]:
    """One field; Foxglove's JSON Schema support needs a single type and no nested arrays."""
    return {"type": json_type, "description": description, **extra}


def proto_schema(cls: Any) -> ChannelSchema:
    """A Foxglove protobuf message: its FileDescriptorSet."""
    data = build_file_descriptor_set(cls).SerializeToString()
    return ChannelSchema(cls.DESCRIPTOR.full_name, "protobuf", "protobuf", data)


T_PROP = prop("number", "time [s], exact; the publish time is round(t*1e9) ns")
_NUMBERS = {"type": "number"}
_JSON_TYPE = {"float": "number", "int": "integer", "str": "string"}


def flat_fields(cls: type) -> list[tuple[str, str]]:
    """(field, type name) of a flat message dataclass, in dataclass order."""
    return [(f.name, f.type if isinstance(f.type, str) else f.type.__name__) for f in fields(cls)]


def flat_schema(cls: type, docs: dict[str, str]) -> ChannelSchema:
    """The schema "walker.<class name>" of a flat message (fields float, int or str), described
    by the first line of the class docstring and `docs` {field: description} ("t" has its
    own)."""
    return json_schema(
        f"walker.{cls.__name__}",
        (cls.__doc__ or "").strip().split("\n")[0],
        {
            name: T_PROP if name == "t" else prop(_JSON_TYPE[type_name], docs[name])
            for name, type_name in flat_fields(cls)
        },
    )


TAG_DETECTIONS = json_schema(
    "walker.TagDetections",
    "AprilTags detected in one tag-camera image (possibly none).",
    {
        "t": T_PROP,
        "detections": prop(
            "array",
            "one entry per tag",
            items={
                "type": "object",
                "properties": {
                    "tag_id": prop("integer", "tag ID"),
                    "camera_T_tag": prop(
                        "array",
                        "4×4 tag pose in the camera optical frame, row-major [m]",
                        items=_NUMBERS,
                    ),
                    "corners_px": prop(
                        "array", "corners u0, v0, u1, v1, u2, v2, u3, v3 [px]", items=_NUMBERS
                    ),
                    "decision_margin": prop("number", "detector margin, NaN if unknown"),
                },
                "required": ["tag_id", "camera_T_tag", "corners_px", "decision_margin"],
            },
        ),
    },
)
RANGE_BEARINGS = json_schema(
    "walker.RangeBearings",
    "Range and bearing to several landmarks seen at one time; entry i of each array is one.",
    {
        "t": T_PROP,
        "landmark_ids": prop("array", "landmark IDs, -1 when unknown", items={"type": "integer"}),
        "ranges_m": prop("array", "ranges [m]", items=_NUMBERS),
        "bearings_rad": prop("array", "bearings [rad], CCW from the robot heading", items=_NUMBERS),
    },
)
DEPTH_EXACT = json_schema(
    "walker.DepthFrameExact", "Exact time of the depth frame on the main topic.", {"t": T_PROP}
)
SCAN_EXACT = json_schema(
    "walker.LaserScanExact",
    "LaserScan fields that foxglove.LaserScan cannot hold exactly.",
    {
        "t": T_PROP,
        "angle_increment": prop("number", "angle between beams [rad]"),
        "range_max": prop("number", "ranges >= range_max are no return [m]"),
        "dtype": prop("string", "numpy dtype of the ranges, e.g. float32"),
    },
)
POSE_EXACT = json_schema(
    "walker.GroundTruthPoseExact",
    "Exact time and heading of the ground-truth pose on the main topic.",
    {"t": T_PROP, "theta": prop("number", "heading [rad], CCW from world +x")},
)
RAW_IMAGE = proto_schema(RawImage)
CAMERA_CALIBRATION = proto_schema(CameraCalibration)
LASER_SCAN = proto_schema(PbLaserScan)
POSE_IN_FRAME = proto_schema(PoseInFrame)
