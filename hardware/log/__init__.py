"""Trial logs: a crash-safe MCAP writer and a replayer that gives back the message dataclasses.

A trial log is one MCAP file (https://mcap.dev) holding every sensor stream, the brake
commands, the calibration, the run's parameters and, in simulation, the ground truth. It
opens in Foxglove and in any MCAP reader; `read_log` turns it back into exactly the
`hardware.messages` dataclasses that were written (bit-exact floats, same array dtypes).

    with LogWriter("trial.mcap", calibration, metadata={"config": cfg, "world": world}) as log:
        for msg in source:
            log.write(msg)                      # topic from the type
        log.write(cmd, topic="/brakes/replayed")  # or an explicit one

    trial = read_log("trial.mcap")   # .calibration .metadata .attachments .topics
    for msg in trial.messages(["/encoders", "/depth/image"]):
        ...

Log format (version 1)
======================

Header: profile "", library "walker-slam log v1 (mcap-python ...)". Chunks are zstd
compressed (lz4 or none if unavailable); the summary and indexes are standard.

Metadata records (MCAP metadata maps str to str, so each dict is stored as one key
"json" holding `json.dumps(dict)`; strict JSON, no NaN):

    calibration   WalkerCalibration.to_dict(); required, a log without it is rejected
    <name>        every dict given as LogWriter(metadata={name: dict}), e.g. "config", "world",
                  "localizer_settings" (settings the source proposes to localizers,
                  experiments.studies.settings.source_settings); LogWriter.add_metadata
                  writes one later, e.g. a simulated trial's "slip" at its end (the true
                  per-wheel slip coefficients, hardware.sim.slip)

Attachments: LogWriter(attachments={name: bytes}), media type application/octet-stream.

Channels: one per stream. `LogWriter.write(msg, topic=None)` uses the type's default
topic below; any other topic may be given (e.g. "/brakes/replayed" for a second brake
command stream). A topic holds a single message type.

    topic                    type               message encoding / schema name
    /encoders                EncoderTicks       json / walker.EncoderTicks
    /brakes/command          BrakeCommand       json / walker.BrakeCommand
    /depth/image             DepthFrame         protobuf / foxglove.RawImage
    /depth/camera_info         companion        protobuf / foxglove.CameraCalibration
    /depth/image/exact         companion        json / walker.DepthFrameExact
    /tags/detections         TagDetections      json / walker.TagDetections
    /range_bearing           RangeBearing       json / walker.RangeBearing
    /range_bearings          RangeBearings      json / walker.RangeBearings
    /odometry/velocity       VelocityOdometry   json / walker.VelocityOdometry
    /imu/gyro                GyroRate           json / walker.GyroRate
    /scan                    LaserScan          protobuf / foxglove.LaserScan
    /scan/exact                companion        json / walker.LaserScanExact
    /groundtruth/pose        GroundTruthPose    protobuf / foxglove.PoseInFrame
    /groundtruth/pose/exact    companion        json / walker.GroundTruthPoseExact
    /collisions              Collision          json / walker.Collision
    /events                  DeviceEvent        json / walker.DeviceEvent
    /compass                 CompassHeading     json / walker.CompassHeading
    /fix                     PositionFix        json / walker.PositionFix

JSON channels have schema encoding "jsonschema"; protobuf channels carry the
FileDescriptorSet of the Foxglove schema (schema encoding "protobuf"). A channel's schema
and channel records are written once, inside the chunk that holds its first message, and
repeated in the summary.

Companion channels complete a Foxglove message with what its schema cannot hold exactly.
For a stream on topic T they are T + "/exact" and, for depth, the camera info on T with a
trailing "/image" replaced by "/camera_info" (else T + "/camera_info"). Each companion
channel has channel metadata {"main_topic": T}, and its message is written just before
the main message with the same log time; the camera info goes with every frame.

Times: publish_time = round(t * 1e9) ns, so t must be finite and >= 0; log_time is the
same unless the writer was given the time the message was recorded (a live recorder
stores the time it fed each message to the pipeline, never earlier than t, so that a
replay in log-time order feeds them in the live run's order; a message's companions
share its log time). The float t itself is stored exactly in every JSON payload ("t"),
for Foxglove messages in the exact companion (their protobuf timestamp holds the same
ns as publish_time).

JSON payloads: compact UTF-8 objects; floats are written with Python's shortest
round-trip repr, so they read back bit-exactly; non-finite floats, which JSON lacks, are
the strings "NaN", "Infinity", "-Infinity" (the protobuf JSON mapping); integers are
JSON integers. Units are SI. Schemas (all fields required):

    walker.EncoderTicks       t [s], left, right [cumulative quadrature counts, int, may be < 0]
    walker.BrakeCommand       t [s], left_nm, right_nm [N·m commanded torque], source [str]
    walker.RangeBearing       t [s], landmark_id [int], range_m [m],
                              bearing_rad [rad, CCW from the robot heading]
    walker.RangeBearings      t [s], landmark_ids [list of int, −1: unknown], ranges_m [list,
                              m], bearings_rad [list, rad]: entry i of each list is one
                              landmark seen at t (the batched form of RangeBearing)
    walker.VelocityOdometry   t [s], v [m/s forward], omega [rad/s yaw rate]; both "NaN":
                              the motion until the next message is not known (a gap)
    walker.GyroRate           t [s], rate_rad_s [rad/s: the gyro's z rate, CCW positive, raw
                              (its bias and scale error included), the mean over the
                              interval since its previous sample]
    walker.Collision          t [s], kind ["front" | "side" | "rear-wheel"], obstacle [str],
                              x, y [m, contact point in the world]
    walker.DeviceEvent        t [s], device [str], event [str: connected | disconnected |
                              reconnected | reset | rebased | gap-motion | stalled |
                              resumed], detail [str]
    walker.CompassHeading     t [s], heading_rad [rad, CCW from the map's +x, (−π, π]],
                              sigma_rad [rad, standard deviation; "NaN" when unknown]
    walker.PositionFix        t [s], x, y [m, the reference point in the map frame],
                              sigma_m [m, standard deviation per axis; "NaN" when unknown]
    walker.TagDetections      t [s], detections: list of {tag_id [int],
                              camera_T_tag [16 numbers: the 4×4 transform, row-major, m],
                              corners_px [8 numbers: u0, v0, ..., u3, v3, px],
                              decision_margin [number, "NaN" when unknown]}
                              (arrays flat because Foxglove's JSON Schema support has no
                              nested arrays; read back as float64 4×4 and 4×2)
    walker.DepthFrameExact    t [s]
    walker.LaserScanExact     t [s], angle_increment [rad], range_max [m],
                              dtype [numpy dtype name of the ranges, e.g. "float32"]
    walker.GroundTruthPoseExact  t [s], theta [rad]

Foxglove messages:

    foxglove.RawImage           timestamp, frame_id "depth_optical", width, height,
                                encoding "16UC1", step 2·width, data: depth in millimetres as
                                little-endian uint16 (0 = invalid)
    foxglove.CameraCalibration  timestamp, frame_id "depth_optical", width, height,
                                distortion_model "plumb_bob", D = 5 zeros,
                                K = [fx 0 cx; 0 fy cy; 0 0 1], R = I, P = [K | 0]
    foxglove.LaserScan          timestamp, frame_id "walker", identity pose,
                                start_angle = angle_min,
                                end_angle = angle_min + (n - 1)·angle_increment,
                                ranges as float64 (float32 values convert exactly, NaN stays
                                NaN, inf stays inf, nothing is clipped at range_max)
    foxglove.PoseInFrame        timestamp, frame_id "world", position (x, y, 0),
                                orientation: yaw theta about z, (0, 0, sin θ/2, cos θ/2)

Crash safety: the writer flushes (closes the current chunk and hands it to the OS) at
least every 0.5 s of wall time (a background thread covers idle periods) and every 0.5 s
of log time, so a killed recorder loses at most the last half second; `fsync=True` also
survives power loss. `close()` (or leaving the `with` block) writes the summary; always
close the writer. `LogWriter.write` may be called from several threads.

Reading: `read_log` scans the file front to back and needs neither summary nor footer (so
it also reads a log that is still being written). Chunk CRCs are checked, and a record
that does not parse is damage: the reader resynchronises on the next intact chunk (or
metadata or attachment record), so a damaged chunk loses its own messages (about half a
second of a recording) and nothing else, and a file cut short loses what came after the
cut. For a damaged log it also reads the summary if that is intact (its CRC holds): the
schemas and channels that the writer declared only inside a lost chunk come from there,
and its indexes name what each damaged span held; without it, the later messages on
those channels cannot be read and are counted as skipped. Metadata records have no CRC:
damage inside one is found when it breaks the record's structure, UTF-8 or JSON.
`LogRecoveryWarning` (one line) names each lost span (its bytes and log times; also
`TrialLog.lost`) and how many messages were recovered; a log without damage gives none,
whether or not its summary is intact. Messages come out in log-time order, ties in file
order, whatever order they were written in. Channels whose schema it does not know are
skipped with an `UnsupportedChannelWarning`, and so are images that are not 16UC1.
Foxglove channels without companions (added by other tools) are read approximately: t
from the timestamp, theta from the quaternion, angle_increment from the end angle,
range_max = inf. `LogError` (one line, naming the file): missing, unreadable or empty
file, not MCAP, truncated in the header or before any message, no readable calibration
record. Decoded depth images are read-only arrays.

The package: `schemas` (the channels' schemas), `codec` (the table of message types: topic,
schemas, encoder and decoder of each), `writer` (LogWriter), `records` (MCAP records at the
byte level), `scan` (the data section read past damage) and `reader` (TrialLog).
"""

from hardware.errors import LogError
from hardware.log.codec import TOPICS, Companions, encode_parts
from hardware.log.reader import (
    LogReader,
    LogRecoveryWarning,
    LostSpan,
    TrialLog,
    UnsupportedChannelWarning,
    read_log,
    replay,
)
from hardware.log.records import MAGIC
from hardware.log.schemas import (
    CAMERA_CALIBRATION,
    DEPTH_EXACT,
    LASER_SCAN,
    POSE_EXACT,
    POSE_IN_FRAME,
    RAW_IMAGE,
    SCAN_EXACT,
    T_PROP,
    TAG_DETECTIONS,
)
from hardware.log.writer import FLUSH_INTERVAL_S, FORMAT, LogWriter

__all__ = [
    "CAMERA_CALIBRATION",
    "DEPTH_EXACT",
    "FLUSH_INTERVAL_S",
    "FORMAT",
    "LASER_SCAN",
    "MAGIC",
    "POSE_EXACT",
    "POSE_IN_FRAME",
    "RAW_IMAGE",
    "SCAN_EXACT",
    "TAG_DETECTIONS",
    "TOPICS",
    "T_PROP",
    "Companions",
    "LogError",
    "LogReader",
    "LogRecoveryWarning",
    "LogWriter",
    "LostSpan",
    "TrialLog",
    "UnsupportedChannelWarning",
    "encode_parts",
    "read_log",
    "replay",
]
