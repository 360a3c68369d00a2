"""ROS bags in: ``sensor_msgs/LaserScan`` lines and a mount angle, as an :class:`ImportedScan`.

Reads ROS 1 ``.bag`` and ROS 2 bags (a folder, or its ``.db3`` / ``.mcap`` file) with
``rosbags``, custom message types included when the bag carries their definitions (ROS 1 always
does; ROS 2 since Iron, and ``rosbags``' writer). What is imported is named by topic specs
``TOPIC[:FIELD]``, ``FIELD`` a dotted path into the message (``laserScan``,
``position[0]``, ``position[tilt_joint]`` — a name looked up in the message's ``name`` list, as
a ``JointState`` has):

- the scan: a ``LaserScan`` message, or a field of one (``/slice:laserScan``); without a
  field, the one ``LaserScan`` field of the message;
- the angle: a number in the scan's own message (``/slice:tiltAngle``), held for that whole line
  (the line was taken at that angle); or a number on its own topic (``/joint_states``, an
  encoder count), sampled at its messages' times and interpolated to each point's time.
  Without a field: a ``JointState``'s one position, a ``std_msgs`` number's ``data``, or the
  scan message's one other number.

A ``LaserScan`` is taken in the sensor's REP-103 frame (``lidar_link`` of ``docs/frames.md``):
point i has the bearing θᵢ = ``angle_min + i·angle_increment``, so its calstation azimuth is
αᵢ = −θᵢ, in the order measured; it is measured at ``header.stamp + i·time_increment``.
A range that is not finite or lies outside [``range_min``, ``range_max``] is an invalid return
(kept, marked). Times are the messages' header stamps when every message used has one, else
the bag's receive times (``stamps="auto"``; or say ``"header"`` or ``"bag"``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calstation.drivers import LidarInfo, LidarLine
from calstation.errors import RecordingImportError
from calstation.recordings.imported import ImportedScan, file_digest, line_rate

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

LASER_SCAN = "sensor_msgs/msg/LaserScan"
JOINT_STATE = "sensor_msgs/msg/JointState"
STAMPS = ("auto", "header", "bag")
CLOCK_MISMATCH_S = 3600.0
"""Header stamps further than this from the bag's receive times are another clock (a
microcontroller's time since boot, say): ``stamps="auto"`` then uses the receive times."""
_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[[^\]]+\])*)$")


class _MissingName(RecordingImportError):
    """A ``[NAME]`` not in a message's ``name`` list (a JointState of other joints)."""


@dataclass(frozen=True)
class TopicSpec:
    """``TOPIC[:FIELD]``: a topic and a dotted path into its messages (empty: the message)."""

    topic: str
    field: str

    @classmethod
    def parse(cls, text: str, option: str) -> TopicSpec:
        """Parse ``TOPIC[:FIELD]`` given to ``option`` (ROS topic names hold no ``:``)."""
        topic, _, path = text.partition(":")
        if not topic.startswith("/") or len(topic) < 2:
            raise RecordingImportError(
                f"{option} {text!r}: expected TOPIC[:FIELD], a topic name starting with /"
            )
        return cls(topic, path.strip())

    def __str__(self) -> str:
        return f"{self.topic}:{self.field}" if self.field else self.topic


# Any: rosbags' messages are dataclasses built at run time from the bag's own definitions
def resolve(msg: Any, path: str, where: str) -> Any:
    """The value at dotted ``path`` in ``msg`` (``a.b``, ``a[2]``, ``position[joint]``);
    ``where`` names the topic and type for errors."""
    value = msg
    done: list[str] = []
    for segment in filter(None, path.split(".")):
        m = _SEGMENT.match(segment)
        if m is None:
            raise RecordingImportError(f"{where}: field path {path!r}: bad segment {segment!r}")
        name, indexes = m.group(1), re.findall(r"\[([^\]]+)\]", m.group(2))
        parent = value
        if not hasattr(value, name) or name == "__msgtype__":
            raise RecordingImportError(
                f"{where}: no field {'.'.join([*done, name])!r}; "
                f"{'.'.join(done) or 'the message'} has {_fields(value)}"
            )
        value = getattr(value, name)
        done.append(name)
        for key in indexes:
            value = _index(value, key, parent, where, ".".join(done))
            done[-1] += f"[{key}]"
    return value


def _index(value: Any, key: str, parent: Any, where: str, field: str) -> Any:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        raise RecordingImportError(f"{where}: {field} is not an array, cannot take [{key}]")
    if re.fullmatch(r"-?\d+", key):
        i = int(key)
        if not -len(value) <= i < len(value):
            raise RecordingImportError(f"{where}: {field} has {len(value)} values, no [{i}]")
        return value[i]
    names = list(getattr(parent, "name", []) or [])
    if key not in names:
        raise _MissingName(
            f"{where}: {field}[{key}]: no {key!r} in the message's name list "
            f"({', '.join(map(str, names)) or 'empty'})"
        )
    i = names.index(key)
    if i >= len(value):
        raise RecordingImportError(
            f"{where}: {field} has {len(value)} values, none for {key!r} (name index {i})"
        )
    return value[i]


def _fields(msg: object) -> str:
    names = [f for f in getattr(msg, "__dataclass_fields__", {}) if f != "__msgtype__"]
    return "fields " + ", ".join(names) if names else f"no fields ({type(msg).__name__})"


def _msgtype(obj: object) -> str:
    return str(getattr(obj, "__msgtype__", type(obj).__name__))


def _number(value: Any, where: str, field: str) -> float:
    """A scalar angle: a number, or an array of exactly one."""
    if isinstance(value, (bool, np.bool_)):
        raise RecordingImportError(f"{where}: {field} is a boolean, not an angle")
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if hasattr(value, "__len__") and not isinstance(value, (str, bytes)):
        if len(value) == 1:
            return _number(value[0], where, field)
        raise RecordingImportError(
            f"{where}: {field} holds {len(value)} values, not one angle: pick one "
            f"({field}[0], or {field}[NAME] for a JointState joint)"
        )
    raise RecordingImportError(
        f"{where}: {field} is a {_msgtype(value)}, not a number: name a numeric field "
        f"({_fields(value)})"
    )


def _numeric_fields(msg: object) -> list[str]:
    return [f for f in getattr(msg, "__dataclass_fields__", {})
            if f != "__msgtype__" and isinstance(getattr(msg, f), (int, float, np.integer,
                                                                   np.floating))
            and not isinstance(getattr(msg, f), bool)]


def _laser_scan_fields(msg: object) -> list[str]:
    return [f for f in getattr(msg, "__dataclass_fields__", {})
            if _msgtype(getattr(msg, f)) == LASER_SCAN]


def _stamp_ns(msg: object) -> int | None:
    """``msg.header.stamp`` in ns, None without a header (or a zero stamp: never set)."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns > 0 else None


@dataclass
class _Collected:
    """What one pass over the bag gathered."""

    scans: list[tuple[int, int | None, Any]]  # (bag time, header stamp, LaserScan)
    held: list[float]  # the angle of each scan, when it is in the scan's own message
    angles: list[tuple[int, int | None, float]]  # (bag time, header stamp, angle)
    scan_type: str = ""
    angle_type: str = ""
    without_name: int = 0  # angle messages without the named joint (left out)
    first_missing: str = ""


def read_rosbag(
    bag: Path | Sequence[Path],
    scan: TopicSpec,
    angle: TopicSpec,
    *,
    angle_unit: str = "rad",
    stamps: str = "auto",
    progress: Callable[[int, int], None] | None = None,
) -> ImportedScan:
    """Read the lines of ``scan`` and the angle ``angle`` from ``bag`` (see the module): one
    bag, or the files of one recording split in several (read as one, in time order).

    ``angle_unit`` is that of the angle values as stored (``deg``, ``rad``, ``counts``);
    ``stamps`` picks the time of each message (:data:`STAMPS`). ``progress(done, total)`` is
    told about the messages read. Raises :class:`RecordingImportError` naming the topic, the
    field and what was found.
    """
    if stamps not in STAMPS:
        raise RecordingImportError(f"stamps {stamps!r} is not one of {', '.join(STAMPS)}")
    bags = [Path(bag)] if isinstance(bag, (str, Path)) else [Path(b) for b in bag]
    if not bags:
        raise RecordingImportError("no bag given")
    got = _collect(bags, scan, angle, progress)
    same = angle.topic == scan.topic
    times, stamp_note = _times(got, same, stamps, scan, angle)
    line_t, angle_t = times
    indexed, notes = _lines(got.scans, line_t, str(scan))
    keep = [i for i, _ in indexed]
    lines = [ln for _, ln in indexed]
    if same:  # held over each line: a reading at its first and last point
        a_t = [t for ln in lines for t in (int(ln.point_times_ns().min()),
                                           int(ln.point_times_ns().max()))]
        a_v = [got.held[i] for i in keep for _ in range(2)]
        angle_t_ns, values = _dedupe(np.array(a_t, np.int64), np.array(a_v, np.float64))
    else:
        angle_t_ns, values = _dedupe(np.asarray(angle_t, np.int64),
                                     np.array([v for _, _, v in got.angles], np.float64))
    if stamp_note:
        notes.insert(0, stamp_note)
    if got.without_name:
        notes.append(f"{got.without_name} messages of {angle.topic} without {angle.field!r} "
                     "(other joints) left out")
    first = got.scans[keep[0]][2]
    source = {
        "tool": "calstation import rosbag",
        "bag": file_digest(bags[0]) if len(bags) == 1 else [file_digest(b) for b in bags],
        "scan": str(scan),
        "scan_type": got.scan_type,
        "angle": str(angle),
        "angle_type": got.angle_type,
        "angle_unit": angle_unit,
        "angle_held_per_line": same,
        "stamps": "bag" if stamps == "bag" or stamp_note is not None else "header",
        "frame_id": str(first.header.frame_id),
        "scans": len(got.scans),
        "angle_messages": len(got.angles) if not same else len(got.scans),
    }
    lidar = LidarInfo(
        vendor="ROS bag import",
        model=f"{got.scan_type} on {scan}",
        serial=str(first.header.frame_id),
        fov_rad=float(abs(first.angle_increment) * max(len(first.ranges) - 1, 0)),
        points_per_line=max(len(ln) for ln in lines),
        line_rate_hz=line_rate([ln.timestamp_ns for ln in lines]),
        range_min_m=float(first.range_min),
        range_max_m=float(first.range_max),
        extra={
            "frame_id": str(first.header.frame_id),
            "angle_min_rad": float(first.angle_min),
            "angle_increment_rad": float(first.angle_increment),
            "time_increment_s": float(first.time_increment),
            "scan_time_s": float(first.scan_time),
            "azimuth": "α = −(angle_min + i·angle_increment) (REP-103 lidar_link)",
        },
    )
    return ImportedScan(lines, angle_t_ns, values, angle_unit, lidar, source, notes)


def _collect(bags: list[Path], scan: TopicSpec, angle: TopicSpec,
             progress: Callable[[int, int], None] | None) -> _Collected:
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    for b in bags:
        if not b.exists():
            raise RecordingImportError(f"bag {b} does not exist")
    bag = bags[0] if len(bags) == 1 else Path(", ".join(map(str, bags)))  # for messages
    try:
        # a ROS 2 bag before Iron carries no type definitions: the standard messages
        # (sensor_msgs, std_msgs, …) are known; a custom type then cannot be decoded
        with AnyReader(bags, default_typestore=get_typestore(Stores.LATEST)) as reader:
            return _collect_from(reader, bag, scan, angle, progress)
    except RecordingImportError:
        raise
    except (AnyReaderError, OSError, ValueError, KeyError, EOFError) as exc:
        raise RecordingImportError(f"bag {bag}: cannot read it ({type(exc).__name__}: {exc})") \
            from exc
    except Exception as exc:  # rosbags' own decoding errors have no common base
        raise RecordingImportError(
            f"bag {bag}: cannot decode it ({type(exc).__name__}: {exc})"
        ) from exc


def _collect_from(reader: AnyReader, bag: Path, scan: TopicSpec, angle: TopicSpec,
                  progress: Callable[[int, int], None] | None) -> _Collected:
    topics = {c.topic: c for c in reader.connections}
    total = sum(c.msgcount for c in reader.connections)
    if not topics or total == 0:
        raise RecordingImportError(f"bag {bag} is empty: it holds no messages")
    listing = ", ".join(f"{t} ({c.msgtype}, {c.msgcount})" for t, c in sorted(topics.items()))
    for spec, option in ((scan, "--scan"), (angle, "--angle")):
        if spec.topic not in topics:
            raise RecordingImportError(
                f"{option} {spec}: bag {bag} has no topic {spec.topic}; its topics: {listing}"
            )
    wanted = [c for c in reader.connections if c.topic in (scan.topic, angle.topic)]
    got = _Collected([], [], [])
    scan_where = f"topic {scan.topic} ({topics[scan.topic].msgtype})"
    angle_where = f"topic {angle.topic} ({topics[angle.topic].msgtype})"
    scan_field = angle_field = None
    for done, (connection, bag_t, raw) in enumerate(reader.messages(connections=wanted), 1):
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as exc:
            raise RecordingImportError(
                f"bag {bag}: topic {connection.topic}: cannot decode a {connection.msgtype} "
                f"message: unknown type or definition ({type(exc).__name__}: {exc})"
            ) from exc
        if connection.topic == scan.topic:
            if scan_field is None:
                scan_field = _scan_field(msg, scan, scan_where)
            ls = resolve(msg, scan_field, scan_where)
            if _msgtype(ls) != LASER_SCAN:
                raise RecordingImportError(
                    f"{scan_where}: {scan_field or 'the message'} is a {_msgtype(ls)}, not a "
                    f"{LASER_SCAN}"
                )
            got.scan_type = connection.msgtype + (f" field {scan_field}" if scan_field else "")
            got.scans.append((int(bag_t), _stamp_ns(ls) or _stamp_ns(msg), ls))
        if connection.topic == angle.topic:
            if angle_field is None:
                angle_field = _angle_field(msg, angle, angle_where,
                                           exclude=scan_field if angle.topic == scan.topic
                                           else None)
            try:
                value = _number(resolve(msg, angle_field, angle_where), angle_where,
                                angle_field)
            except _MissingName as exc:  # another publisher's joints on the same topic
                got.without_name += 1
                got.first_missing = got.first_missing or str(exc)
                continue
            got.angle_type = connection.msgtype + f" field {angle_field}"
            if angle.topic == scan.topic:
                got.held.append(value)
            else:
                got.angles.append((int(bag_t), _stamp_ns(msg), value))
        if progress is not None:
            progress(done, total)
    if not got.scans:
        raise RecordingImportError(f"--scan {scan}: topic {scan.topic} has no messages in {bag}")
    if not got.held and not got.angles:
        if got.first_missing:
            raise RecordingImportError(got.first_missing)
        raise RecordingImportError(
            f"--angle {angle}: topic {angle.topic} has no messages in {bag}: the angle is missing"
        )
    if got.held and len(got.held) != len(got.scans):
        raise RecordingImportError(
            f"--angle {angle}: {got.without_name} of the {len(got.scans)} scans have no angle: "
            f"{got.first_missing}"
        )
    return got


def _scan_field(msg: object, spec: TopicSpec, where: str) -> str:
    if spec.field or _msgtype(msg) == LASER_SCAN:
        return spec.field
    fields = _laser_scan_fields(msg)
    if len(fields) == 1:
        return fields[0]
    raise RecordingImportError(
        f"--scan {spec}: {where} is not a {LASER_SCAN} and holds "
        + (f"{len(fields)} LaserScan fields ({', '.join(fields)})" if fields
           else f"none ({_fields(msg)})")
        + f": name one, as {spec.topic}:FIELD"
    )


def _angle_field(msg: Any, spec: TopicSpec, where: str, exclude: str | None) -> str:
    if spec.field:
        return spec.field
    mtype = _msgtype(msg)
    if mtype == JOINT_STATE:
        names = list(msg.name)
        if len(msg.position) == 1:
            return "position"
        raise RecordingImportError(
            f"--angle {spec}: {where} has {len(msg.position)} joint positions "
            f"({', '.join(names) or 'unnamed'}): name one, as {spec.topic}:position[NAME]"
        )
    if hasattr(msg, "data") and mtype.startswith("std_msgs/"):
        return "data"
    numbers = [f for f in _numeric_fields(msg) if f != exclude]
    if exclude is not None and len(numbers) == 1:
        return numbers[0]
    raise RecordingImportError(
        f"--angle {spec}: name the angle's field, as {spec.topic}:FIELD; {where} has "
        f"{_fields(msg)}"
    )


def _times(got: _Collected, same: bool, stamps: str, scan: TopicSpec, angle: TopicSpec,
           ) -> tuple[tuple[NDArray[np.int64], NDArray[np.int64]], str | None]:
    """The lines' and the angle samples' times on one clock, and a note when the receive times
    had to replace header stamps."""
    scan_bag = np.array([b for b, _, _ in got.scans], np.int64)
    angle_bag = np.array([b for b, _, _ in got.angles], np.int64)
    scan_hdr = [h for _, h, _ in got.scans]
    angle_hdr = [h for _, h, _ in got.angles]
    have = all(h is not None for h in scan_hdr) and (same or all(h is not None
                                                                 for h in angle_hdr))
    if stamps == "bag":
        return (scan_bag, angle_bag), None
    if stamps == "header" and not have:
        missing = scan if any(h is None for h in scan_hdr) else angle
        raise RecordingImportError(
            f"--stamps header: topic {missing.topic} has messages without a header stamp; "
            "use --stamps bag (the bag's receive times)"
        )
    if not have:
        which = scan.topic if any(h is None for h in scan_hdr) else angle.topic
        return (scan_bag, angle_bag), (
            f"times: the bag's receive times (topic {which} has no header stamps)")
    hdr_s = np.array(scan_hdr, np.int64)
    hdr_a = np.array(angle_hdr, np.int64) if not same else angle_bag
    off = np.median(np.concatenate([hdr_s - scan_bag] + ([] if same else [hdr_a - angle_bag])))
    if stamps == "auto" and abs(off) * 1e-9 > CLOCK_MISMATCH_S:
        return (scan_bag, angle_bag), (
            f"times: the bag's receive times (the header stamps are {off * 1e-9:+.0f} s from "
            "them: another clock)")
    return (hdr_s, hdr_a), None


def _lines(scans: Sequence[tuple[int, int | None, Any]], line_t: NDArray[np.int64],
           where: str) -> tuple[list[tuple[int, LidarLine]], list[str]]:
    """Each non-empty LaserScan as a calstation line (α = −θ, measured order, REP-117
    invalids) with its message's index, in time order."""
    lines: list[tuple[int, LidarLine]] = []
    empty = invalid = 0
    order_broken = 0
    last = None
    for i, (_, _, ls) in enumerate(scans):
        ranges = np.asarray(ls.ranges, dtype=np.float64)
        n = len(ranges)
        if n == 0:
            empty += 1
            continue
        inc = float(ls.angle_increment)
        amin, amax = float(ls.angle_min), float(ls.angle_max)
        _check_geometry(ls, i, n, where)
        if n > 1 and (inc == 0.0 or not math.isfinite(inc)):
            raise RecordingImportError(
                f"--scan {where}: message {i}: angle_increment is {inc} for {n} ranges"
            )
        if n > 1 and abs((amax - amin) / inc + 1 - n) > 1.5:
            raise RecordingImportError(
                f"--scan {where}: message {i}: mismatched lengths: {n} ranges, but angle_min "
                f"{amin:.6g} to angle_max {amax:.6g} in steps of {inc:.6g} rad is "
                f"{(amax - amin) / inc + 1:.1f} bearings"
            )
        intensities = np.asarray(ls.intensities, dtype=np.float64)
        if len(intensities) not in (0, n):
            raise RecordingImportError(
                f"--scan {where}: message {i}: mismatched lengths: {n} ranges but "
                f"{len(intensities)} intensities"
            )
        theta = amin + np.arange(n, dtype=np.float64) * inc
        valid = np.isfinite(ranges) & (ranges >= float(ls.range_min)) & (
            ranges <= float(ls.range_max))
        invalid += int(n - np.count_nonzero(valid))
        t = int(line_t[i])
        if last is not None and t <= last:
            order_broken += 1
        last = t
        lines.append((i, LidarLine(
            timestamp_ns=t,
            azimuth_rad=-theta,
            range_m=ranges,
            valid=valid,
            point_period_ns=float(ls.time_increment) * 1e9,
            intensity=intensities if len(intensities) else None,
        )))
    if not lines:
        raise RecordingImportError(f"--scan {where}: every LaserScan is empty (no ranges)")
    notes = []
    if empty:
        notes.append(f"{empty} empty LaserScans (no ranges) left out")
    if invalid:
        notes.append(f"{invalid} returns invalid (inf, nan or outside range_min..range_max): "
                     "kept, marked invalid")
    if all(float(ls.time_increment) == 0.0 for _, _, ls in scans if len(ls.ranges)):
        notes.append("time_increment is 0: every point of a line is given its line's time")
    if order_broken:
        lines.sort(key=lambda item: item[1].timestamp_ns)
        notes.append(f"{order_broken} scans stamped before the one received before them: "
                     "sorted by time")
    return lines, notes


MAX_LINE_SPAN_S = 10.0
"""Longest time the ``n`` returns of one LaserScan may span (``|time_increment|·(n − 1)``): a
line scanner sweeps a line in well under a second; past this the times are not a scan's (a huge
``time_increment`` would overflow the points' nanosecond times)."""


def _check_geometry(ls: Any, i: int, n: int, where: str) -> None:
    """A LaserScan's bearings, times and range limits must be numbers: a NaN or infinite
    ``angle_min`` would give every return a NaN azimuth, and a NaN ``time_increment`` NaN
    times, each read as valid (an infinite ``range_max`` only means no upper limit). The ``n``
    returns' times must span at most :data:`MAX_LINE_SPAN_S`."""
    fields = {"angle_min": ls.angle_min, "angle_max": ls.angle_max,
              "angle_increment": ls.angle_increment, "time_increment": ls.time_increment,
              "range_min": ls.range_min}
    for name, value in fields.items():
        if not math.isfinite(float(value)):
            raise RecordingImportError(
                f"--scan {where}: message {i}: {name} is {float(value)}, not a number; the "
                "scan's bearings and times cannot be known"
            )
    if math.isnan(float(ls.range_max)):
        raise RecordingImportError(
            f"--scan {where}: message {i}: range_max is nan, not a number (inf: no limit)"
        )
    span = abs(float(ls.time_increment)) * max(n - 1, 0)
    if span > MAX_LINE_SPAN_S:
        raise RecordingImportError(
            f"--scan {where}: message {i}: time_increment is {float(ls.time_increment):.6g} s: "
            f"its {n} ranges would span {span:.6g} s, longer than any line scanner sweeps a "
            f"line ({MAX_LINE_SPAN_S:g} s)"
        )


def _dedupe(t: NDArray[np.int64], v: NDArray[np.float64]
            ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Samples in time order with one value per time (the last received)."""
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.ones(len(t), bool)
    keep[:-1] = t[1:] != t[:-1]
    return t[keep], v[keep]
