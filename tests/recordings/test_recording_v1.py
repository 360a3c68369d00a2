"""Version-1 recordings (JSON messages with base64 arrays) stay readable and calibrate as before.

The fixtures in ``tests/data/v1`` were written by calstation's version-1 writer from a small
simulated run (``tests/data/v1/recipe.yaml``); ``expected.json`` holds the H computed from them
and a digest of the arrays read, both taken before the format changed.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from calstation import plugins
from calstation.engine.frames import Extrinsics
from calstation.engine.initial import initial_calibration
from calstation.recipes import load_recipe
from calstation.recordings.channels import FORMAT_VERSION
from calstation.recordings.reader import read_recording
from calstation.recordings.recorded import Recording
from calstation.recordings.writer import RecordingWriter

DATA = Path(__file__).resolve().parents[1] / "data" / "v1"
EXPECTED = json.loads((DATA / "expected.json").read_text(encoding="utf-8"))


def _digest(rec: Recording) -> str:
    h = hashlib.sha256()
    for a in (rec.line_timestamp_ns, rec.t_ns, rec.azimuth_rad, rec.range_m, rec.valid,
              rec.encoder_t_ns, rec.encoder_count):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _read(path: Path) -> Recording:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return read_recording(path)


def _rewrite_as_v2(rec: Recording, path: Path) -> Recording:
    """The same scan written by today's writer, from the lines and readings of ``rec``."""
    loaded = load_recipe(DATA / "recipe.yaml")
    with RecordingWriter(
        path,
        kind=rec.kind,
        lidar_info=rec.lidar_info,
        counts_per_revolution=rec.counts_per_revolution,
        encoder_direction=rec.encoder_direction,
        encoder_latency_s=rec.encoder_latency_s,
        recipe=loaded,
        metadata={"truth": rec.metadata["truth"]},
    ) as w:
        w.write_encoder(rec.encoder_samples())
        for line in rec.lines():
            w.write_line(line)
        for status in rec.turntable:
            w.write_turntable(status)
    return _read(path)


@pytest.mark.parametrize("kind", ["static", "spin"])
def test_v1_fixture_reads_the_same_arrays(kind: str) -> None:
    rec = _read(DATA / f"{kind}.mcap")
    want = EXPECTED["arrays"][kind]
    assert rec.metadata["calstation"]["format_version"] == 1 < FORMAT_VERSION
    assert (rec.n_lines, rec.n_points) == (want["n_lines"], want["n_points"])
    assert (len(rec.encoder_t_ns), len(rec.turntable)) == (want["n_encoder"], want["n_turntable"])
    assert _digest(rec) == want["arrays_sha256"]
    assert rec.truth is not None and rec.calibration is None
    assert rec.recipe_text == (DATA / "recipe.yaml").read_text(encoding="utf-8")


def test_v1_fixture_calibrates_to_the_same_h(tmp_path: Path) -> None:
    """Initial calibration gives the stored H exactly; periodicity fine-tuning gives the same H
    from the v1 file as from the same scan rewritten in version 2, and the stored H."""
    recipe = load_recipe(DATA / "recipe.yaml").recipe
    # the stored H was fitted before the lidar's range model: fitted here without one too
    recipe = recipe.model_copy(update={
        "calibration": recipe.calibration.model_copy(update={"range_model": "none"})})
    static = _read(DATA / "static.mcap")
    initial = initial_calibration(static, recipe.fixtures.static_target,
                                  recipe.calibration.initial)
    want_initial = Extrinsics.from_dict(EXPECTED["initial"])
    np.testing.assert_allclose(initial.H.as_vector(), want_initial.as_vector(), rtol=0, atol=1e-12)

    spin_v1 = _read(DATA / "spin.mcap")
    spin_v2 = _rewrite_as_v2(spin_v1, tmp_path / "spin.mcap")
    assert spin_v2.metadata["calstation"]["format_version"] == FORMAT_VERSION
    assert _digest(spin_v2) == _digest(spin_v1)
    strategy = plugins.strategy("periodicity")
    got_v1 = strategy.run(spin_v1, initial.H, recipe, lambda m, f: None).H
    got_v2 = strategy.run(spin_v2, initial.H, recipe, lambda m, f: None).H
    np.testing.assert_array_equal(got_v1.as_vector(), got_v2.as_vector())
    want = Extrinsics.from_dict(EXPECTED["periodicity"]).as_vector()
    # loose enough to survive an improved optimiser, tight against a misread recording
    np.testing.assert_allclose(got_v1.as_vector()[:3], want[:3], atol=5e-4)
    np.testing.assert_allclose(got_v1.as_vector()[3:], want[3:], atol=np.radians(0.1))
