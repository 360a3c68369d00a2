"""Files beside the recordings: point clouds as PLY, and calibration files.

:func:`write_ply` and :func:`read_ply` keep a reconstructed cloud (``calstation reconstruct``);
:func:`save_calibration` writes a calibration file (``calstation calibrate -o``);
:func:`load_calibration_file` reads a calibration written by ``calstation calibrate`` or
``export`` (YAML or JSON) back into H and its lidar–encoder time offset. Every problem is a
:class:`~calstation.errors.RecordingError` that names the file and the field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.atomic import write_atomic
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.engine.rangemodel import RangeModel
from calstation.errors import CalibrationError, RecordingError

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult


def write_ply(path: str | Path, points: ArrayLike) -> None:
    """Write (N, 3) points (metres) as a binary little-endian PLY (float32 x, y, z), whole or
    not at all (:func:`calstation.atomic.write_atomic`: a folder, device or FIFO named as
    ``path`` is refused, and so is a missing folder).

    Readable by Open3D, MeshLab and CloudCompare. Non-finite points are an error.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise RecordingError(f"PLY points must have shape (N, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts).all(axis=1)).sum())
        raise RecordingError(f"{bad} of {len(pts)} points are not finite; cannot write {path}")
    header = (
        "ply\n"
        "format binary_little_endian 1.0\n"
        "comment calstation point cloud, frame D, metres\n"
        f"element vertex {len(pts)}\n"
        "property float x\n"
        "property float y\n"
        "property float z\n"
        "end_header\n"
    ).encode("ascii")
    write_atomic(path, header + np.ascontiguousarray(pts, dtype="<f4").tobytes(), "PLY file")


def read_ply(path: str | Path) -> NDArray[np.float64]:
    """Read the (N, 3) points of a PLY written by :func:`write_ply` (or any float32 x/y/z
    binary little-endian vertex-only PLY), metres."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise RecordingError(f"cannot read PLY {p}: {exc}") from exc
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise RecordingError(f"{p} is not a PLY file")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise RecordingError(f"{p}: only binary little-endian PLY is supported")
    props = [h.split()[-1] for h in header if h.startswith("property")]
    n = next((int(h.split()[-1]) for h in header if h.startswith("element vertex")), None)
    if n is None or props != ["x", "y", "z"] or any(
        h.startswith("property") and h.split()[1] != "float" for h in header
    ):
        raise RecordingError(f"{p}: expected a vertex element with float x, y, z only")
    body = data[end + len(b"end_header\n") :]
    if len(body) < n * 12:
        raise RecordingError(f"{p}: truncated ({len(body)} bytes for {n} vertices)")
    return np.frombuffer(body[: n * 12], dtype="<f4").reshape(n, 3).astype(np.float64)


# --- calibration files ---------------------------------------------------------------------
def save_calibration(result: CalibrationResult, path: str | Path) -> Path:
    """Write ``result`` as a calibration file, YAML for ``.yaml``/``.yml`` and JSON otherwise
    (what :meth:`~calstation.engine.result.CalibrationResult.save` writes), whole or not at all
    (:func:`calstation.atomic.write_atomic`); the path written."""
    return result.save(path, "calibration file")


def load_extrinsics(path: str | Path, *, source: str = "calibration") -> Extrinsics:
    """Read H from a file, in metres and radians.

    ``source="calibration"``: a calibration result (YAML or JSON) with a mapping ``H`` holding
    tx, ty, tz, rx, ry, rz. ``source="truth"``: a simulator ``truth.json`` with tx..rz at top level.
    Raises :class:`RecordingError` naming the file and field on any problem.
    """
    return load_calibration_file(path, source=source)[0]


def load_calibration_file(
    path: str | Path, *, source: str = "calibration"
) -> tuple[Extrinsics, float | None]:
    """H (as :func:`load_extrinsics`) and the encoder latency (s) from one read of the file: the
    one a calibration estimated (``encoder_latency_s``), or the true one of a simulator
    ``truth.json`` (``encoder.latency_s``); None when the file has none. Raises
    :class:`RecordingError` naming the file and field on any problem."""
    if source not in ("calibration", "truth"):
        raise ValueError(f"source must be 'calibration' or 'truth', not {source!r}")
    from calstation.yamlsafe import read_text_file

    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{source} file {p} does not exist")
    try:  # a regular file of bounded size only (a FIFO would block forever)
        text = read_text_file(p, f"{source} file", 10_000_000)
    except ValueError as exc:
        raise RecordingError(f"cannot read {source} file {p}: {exc}") from None
    data = _parse_mapping(p, text, source)
    if source == "calibration":
        if "H" not in data:
            raise RecordingError(
                f"calibration file {p} has no 'H' mapping "
                "(expected H: {tx, ty, tz, rx, ry, rz} in metres and radians)"
            )
        h = data["H"]
        where = "H."
        if not isinstance(h, Mapping):
            raise RecordingError(f"calibration file {p}: 'H' must be a mapping, got {h!r}")
        latency, latency_field = data.get("encoder_latency_s"), "encoder_latency_s"
    else:
        h, where = data, ""
        encoder = data.get("encoder")
        latency = encoder.get("latency_s") if isinstance(encoder, Mapping) else None
        latency_field = "encoder.latency_s"
    values: dict[str, float] = {}
    for name in PARAMETER_NAMES:
        if name not in h:
            if name == "rx":
                values[name] = 0.0
                continue
            raise RecordingError(f"{source} file {p} is missing field {where}{name}")
        values[name] = _finite(h[name], f"{source} file {p}: field {where}{name}", "")
    seconds = None if latency is None else _finite(
        latency, f"{source} file {p}: field {latency_field}", " of seconds")
    return Extrinsics(**values), seconds


def load_range_model(path: str | Path, *, source: str = "calibration") -> RangeModel:
    """The lidar's range model (DESIGN §9) from a calibration file (``range_offset``,
    ``range_scale``, as :func:`load_calibration_file` reads its H) or the true one of a
    simulator ``truth.json`` (the same top-level keys); none (the identity) when the file has
    none. Raises :class:`RecordingError` naming the file and field on any problem."""
    from calstation.yamlsafe import read_text_file

    p = Path(path)
    try:
        text = read_text_file(p, f"{source} file", 10_000_000)
    except ValueError as exc:
        raise RecordingError(f"cannot read {source} file {p}: {exc}") from None
    data = _parse_mapping(p, text, source)
    values = {}
    for name in ("range_offset", "range_scale"):
        value = data.get(name)
        values[name] = 0.0 if value is None else _finite(
            value, f"{source} file {p}: field {name}", "")
    try:
        return RangeModel(values["range_offset"], values["range_scale"])
    except CalibrationError as exc:
        raise RecordingError(f"{source} file {p}: {exc}") from None


def _finite(value: object, what: str, unit: str) -> float:
    """``value`` as a float; :class:`RecordingError` (``what`` must be a finite number) if it
    is not one."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RecordingError(f"{what} must be a finite number{unit}, got {value!r}")
    return float(value)


def _parse_mapping(p: Path, text: str, source: str) -> Mapping[str, object]:
    data: object
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise RecordingError(
                f"{source} file {p} is not valid JSON: {exc.msg} at line {exc.lineno}"
            ) from exc
    else:
        import yaml

        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            line = f" at line {mark.line + 1}" if mark is not None else ""
            raise RecordingError(f"{source} file {p} is not valid YAML/JSON{line}") from exc
    if not isinstance(data, Mapping):
        raise RecordingError(f"{source} file {p} must hold a mapping, got {type(data).__name__}")
    return data
