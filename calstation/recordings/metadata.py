"""A recording's metadata records: each a name and a mapping whose values are JSON-encoded.

The writer encodes them (:func:`encode_metadata`) and always writes ``calstation``, ``lidar`` and
``encoder`` (:func:`station_records`) and, when known, ``calibration``
(:func:`calibration_record`); the reader decodes them (:func:`decode_metadata`).
``docs/recording-format.md`` lists the records and their keys.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from calstation.drivers import LidarInfo
from calstation.engine.frames import Extrinsics
from calstation.errors import RecordingError
from calstation.recordings.channels import FORMAT_VERSION


class RecipeInfo(Protocol):
    """The recipe a scan is taken with, as its recording keeps it: ``name`` and ``sha256`` in the
    ``calstation`` metadata record, ``text`` as the attachment ``recipe.yaml``.
    :class:`calstation.recipes.LoadedRecipe` is one."""

    @property
    def name(self) -> str:
        """The recipe's name."""
        ...

    @property
    def text(self) -> str:
        """The recipe's YAML text, as read."""
        ...

    @property
    def sha256(self) -> str:
        """The sha256 of ``text`` (UTF-8), hex."""
        ...


def _json_default(obj: object) -> object:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, Mapping):
        return dict(obj)
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def encode_metadata(name: str, data: Mapping[str, object]) -> dict[str, str]:
    """Record ``name``'s values JSON-encoded (NumPy values, paths, sets and tuples as their JSON
    equivalents); :class:`RecordingError` names the key that cannot be stored."""
    out: dict[str, str] = {}
    for key, value in data.items():
        try:
            out[str(key)] = json.dumps(value, default=_json_default)
        except (TypeError, ValueError) as exc:
            raise RecordingError(
                f"metadata {name!r} key {key!r} cannot be stored as JSON: {exc}"
            ) from exc
    return out


def station_records(
    kind: str,
    station_id: str,
    recipe: RecipeInfo | None,
    created_ns: int,
    lidar_info: LidarInfo,
    encoder: tuple[int, int, float],
) -> dict[str, dict[str, object]]:
    """The metadata records a writer always writes: ``calstation`` (the scan, its station and
    recipe), ``lidar`` and ``encoder`` (counts per revolution, direction, latency in s)."""
    counts_per_revolution, direction, latency_s = encoder
    return {
        "calstation": {
            "format_version": FORMAT_VERSION,
            "kind": kind,
            "station_id": station_id,
            "recipe_name": recipe.name if recipe is not None else "",
            "recipe_sha256": recipe.sha256 if recipe is not None else "",
            "created_ns": created_ns,
        },
        "lidar": lidar_info.as_dict(),
        "encoder": {
            "counts_per_revolution": int(counts_per_revolution),
            "direction": int(direction),
            "latency_s": float(latency_s),
        },
    }


def calibration_record(H: Extrinsics, source: str) -> dict[str, object]:
    """The ``calibration`` record: H's tx..rz and where it came from (``initial``, ``fine``, …)."""
    return {**H.as_dict(), "source": source}


def decode_metadata(
    p: Path, name: str, raw: Mapping[str, str]
) -> dict[str, Any]:  # Any: JSON from the file, read key by key by the reader
    """Record ``name`` of recording ``p`` with its values decoded from JSON (a value that is not
    JSON kept as its string)."""
    out: dict[str, Any] = {}  # Any: as returned
    for key, value in raw.items():
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value  # written by another tool: keep the plain string
    return out
