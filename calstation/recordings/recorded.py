"""A recording read back: :class:`Recording`, the engine's scan with what the file says about it.

:func:`calstation.recordings.reader.read_recording` builds it from an MCAP file.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from calstation.drivers import EncoderSample, LidarInfo, LidarLine, TurntableStatus
from calstation.engine.frames import Extrinsics
from calstation.engine.scan import Scan
from calstation.errors import CalstationError, RecordingError
from calstation.recordings.channels import RECIPE_ATTACHMENT

_H_KEYS = ("tx", "ty", "tz", "rx", "ry", "rz")


@dataclass(frozen=True, kw_only=True)
class Recording(Scan):
    """A scan read back from an MCAP file (:func:`~calstation.recordings.reader.read_recording`):
    the engine's :class:`~calstation.engine.scan.Scan` (its arrays) with what the file says
    about it.

    - ``kind``: ``static``, ``spin``, ``cube`` (metadata ``calstation.kind``).
    - ``metadata``: every metadata record, decoded (``calstation``, ``lidar``, ``encoder``,
      ``truth``, ``calibration``, …); ``lidar_info`` the lidar's identity and settings.
    - ``turntable``: the turntable status messages; ``truncated``: the file ended early (a
      writer killed mid-scan) and what it held was read.
    - ``attachments``: attachment name → bytes (``recipe.yaml``).
    """

    kind: str
    metadata: dict[str, dict[str, Any]]  # Any: decoded JSON (metadata.decode_metadata)
    lidar_info: LidarInfo
    turntable: list[TurntableStatus]
    truncated: bool
    attachments: dict[str, bytes] = field(default_factory=dict)

    @property
    def truth(self) -> Extrinsics | None:
        """The true H of simulated data (metadata ``truth``, keys tx..rz), else None."""
        return self._extrinsics("truth")

    @property
    def calibration(self) -> Extrinsics | None:
        """The H known when the scan was taken (metadata ``calibration``, keys tx..rz, with
        ``source``: ``initial``, ``fine``, ``truth``, …), else None."""
        return self._extrinsics("calibration")

    def _extrinsics(self, name: str) -> Extrinsics | None:
        """The H in metadata record ``name`` (keys tx..rz), None without that record."""
        data = self.metadata.get(name)
        if data is None:
            return None
        try:
            return Extrinsics.from_dict({k: data[k] for k in data if k in _H_KEYS})
        except CalstationError as exc:
            raise RecordingError(
                f"recording {self.path}: metadata '{name}' is invalid: {exc}"
            ) from exc

    @property
    def recipe_text(self) -> str | None:
        """The recipe the scan was taken with (attachment ``recipe.yaml``), if stored."""
        data = self.attachments.get(RECIPE_ATTACHMENT)
        return None if data is None else data.decode("utf-8")

    # --- lines and encoder readings ------------------------------------------------------
    def lines(self) -> Iterator[LidarLine]:
        """The lidar lines, in order, as :class:`~calstation.drivers.LidarLine` (array views)."""
        bounds = self.line_bounds()
        for i in range(self.n_lines):
            a, b = int(bounds[i]), int(bounds[i + 1])
            ts = int(self.line_timestamp_ns[i])
            explicit = self.line_has_offsets is None or bool(self.line_has_offsets[i])
            period = 0.0 if self.line_point_period_ns is None else float(
                self.line_point_period_ns[i]
            )
            yield LidarLine(
                timestamp_ns=ts,
                azimuth_rad=self.azimuth_rad[a:b],
                range_m=self.range_m[a:b],
                valid=self.valid[a:b],
                point_period_ns=period,
                time_offset_ns=(self.t_ns[a:b] - ts) if explicit else None,
                intensity=None if self.intensity is None else self.intensity[a:b],
            )

    def encoder_samples(self) -> list[EncoderSample]:
        """The encoder readings as :class:`~calstation.drivers.EncoderSample`, in time order."""
        return [
            EncoderSample(int(t), int(c))
            for t, c in zip(self.encoder_t_ns.tolist(), self.encoder_count.tolist(), strict=True)
        ]
