"""Recordings in one import: the names of the recording module before it was split.

A recording is each scan written to MCAP while it is acquired, and read back as numpy arrays
(``docs/recording-format.md``). The code lives in one module per job:

- :mod:`calstation.recordings.channels`: the layout (format version, channels and schemas,
  reserved metadata names, the recipe attachment); :mod:`calstation.recordings.metadata`: the
  metadata records, encoded and decoded;
- :mod:`calstation.recordings.writer`: :class:`RecordingWriter` and the process's live sink;
- :mod:`calstation.recordings.reader`: :func:`read_recording` (version 2), with
  :mod:`calstation.recordings.v1` (version 1) and :mod:`calstation.recordings.collected` (the
  reader's working state);
- :mod:`calstation.recordings.recorded`: :class:`Recording`, what :func:`read_recording` returns.

This module only re-exports their public names, so that ``from calstation.recordings.recording
import read_recording, RecordingWriter, Recording`` (and the old flat path
``calstation.recording``, :data:`calstation._compat.MOVED`) keep working. It cannot hold
:class:`Recording` itself: the reader builds recordings, so the class's module is below the
reader's, and this module is above both. calstation's own code imports each name from its home
module.
"""

from __future__ import annotations

from calstation.engine.scan import encoder_angle as encoder_angle
from calstation.recordings.channels import (
    CHANNELS as CHANNELS,
    CLOUD_TOPIC as CLOUD_TOPIC,
    ENCODER_TOPIC as ENCODER_TOPIC,
    FORMAT_VERSION as FORMAT_VERSION,
    LIDAR_TOPIC as LIDAR_TOPIC,
    PLATTER_TF_TOPIC as PLATTER_TF_TOPIC,
    RECIPE_ATTACHMENT as RECIPE_ATTACHMENT,
    RESERVED_METADATA as RESERVED_METADATA,
    SCAN_TOPIC as SCAN_TOPIC,
    STATIC_TF_TOPIC as STATIC_TF_TOPIC,
    TURNTABLE_SCHEMA as TURNTABLE_SCHEMA,
    TURNTABLE_TOPIC as TURNTABLE_TOPIC,
    channel_schema as channel_schema,
)
from calstation.recordings.collected import Buffer as Buffer
from calstation.recordings.reader import (
    RecordingTruncatedWarning as RecordingTruncatedWarning,
    read_recording as read_recording,
)
from calstation.recordings.recorded import Recording as Recording
from calstation.recordings.v1 import (
    V1_AZIMUTH_DTYPE as V1_AZIMUTH_DTYPE,
    V1_INTENSITY_DTYPE as V1_INTENSITY_DTYPE,
    V1_RANGE_DTYPE as V1_RANGE_DTYPE,
    V1_TIME_OFFSET_DTYPE as V1_TIME_OFFSET_DTYPE,
    V1_VALID_DTYPE as V1_VALID_DTYPE,
)
from calstation.recordings.writer import (
    DEFAULT_CHUNK_SIZE as DEFAULT_CHUNK_SIZE,
    DEFAULT_CLOUD_POINTS as DEFAULT_CLOUD_POINTS,
    DEFAULT_FLUSH_INTERVAL_S as DEFAULT_FLUSH_INTERVAL_S,
    LiveSink as LiveSink,
    RecordingWriter as RecordingWriter,
    live_sink as live_sink,
    set_live_sink as set_live_sink,
)
