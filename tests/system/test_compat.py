"""Old import paths (the flat layout before the packages) keep working for one release."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from calstation._compat import MOVED


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_path_gives_the_same_module_with_a_deprecation_warning(old: str) -> None:
    code = (
        "import importlib, warnings\n"
        "warnings.simplefilter('error', DeprecationWarning)\n"
        f"new = importlib.import_module({MOVED[old]!r})\n"
        "try:\n"
        f"    importlib.import_module({old!r})\n"
        "except DeprecationWarning as w:\n"
        "    print('warned:', w)\n"
        "warnings.simplefilter('ignore', DeprecationWarning)\n"
        f"old = importlib.import_module({old!r})\n"
        "print('same' if old is new else 'different', old.__spec__.name)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    # a moved package's submodule warns for the package, which is imported first
    first = next(p for p in (old.rsplit(".", 1)[0], old) if p in MOVED)
    assert f"warned: {first} moved to {MOVED[first]}" in out.stdout
    assert f"same {MOVED[old]}" in out.stdout


def test_from_an_old_path_imports_the_objects_of_the_new_one() -> None:
    with pytest.warns(DeprecationWarning, match="calstation.recipe moved to calstation.recipes"):
        sys.modules.pop("calstation.recipe", None)
        from calstation.recipe import load_recipe
    assert load_recipe is importlib.import_module("calstation.recipes").load_recipe


def test_the_recording_module_gives_the_writer_the_reader_and_the_recording() -> None:
    """``calstation.recordings.recording`` was split (writer, reader, recorded, …); it and the old
    ``calstation.recording`` still give the very same objects."""
    from calstation.recordings import reader, recorded, recording, writer

    homes = (reader.read_recording, writer.RecordingWriter, recorded.Recording)
    assert (recording.read_recording, recording.RecordingWriter, recording.Recording) == homes
    with pytest.warns(DeprecationWarning, match="calstation.recording moved"):
        sys.modules.pop("calstation.recording", None)
        from calstation.recording import Recording, RecordingWriter, read_recording
    assert (read_recording, RecordingWriter, Recording) == homes


def test_names_of_the_flat_station_module_import_from_the_package_with_a_warning() -> None:
    from calstation.station import runs

    with pytest.warns(DeprecationWarning, match=r"calstation.station.start_run moved to "
                                                r"calstation.station.runs.start_run"):
        from calstation.station import start_run
    assert start_run is runs.start_run
    with pytest.raises(ImportError):
        from calstation.station import no_such_name  # noqa: F401
