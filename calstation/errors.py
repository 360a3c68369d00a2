"""One root error for calstation, with a subclass per area.

Every error calstation raises on bad input or a failed step derives from :class:`CalstationError`;
the CLI prints its message (which names the file, field or line) instead of a traceback.
"""

from __future__ import annotations


class CalstationError(Exception):
    """Root of every error calstation raises on purpose.

    ``option``: the name of the library parameter the error refuses (``accept``, ``force``),
    when it is about one. The library words its errors without the command line's flags, since
    the web station calls it too; the command line names its flag (``--accept``) in front of
    the message.
    """

    option: str | None = None

    def __init__(self, *args: object, option: str | None = None) -> None:
        super().__init__(*args)
        if option is not None:
            self.option = option


class FrameError(CalstationError, ValueError):
    """Invalid frame, transform or encoder parameters."""


class RecipeError(CalstationError):
    """A recipe file is missing, malformed or fails validation."""


class RecordingError(CalstationError):
    """A recording is missing, unreadable, truncated past use, or inconsistent."""


class RecordingUnavailable(RecordingError):
    """A stored recording that cannot be used as stored: missing, or changed (its sha256)."""


class RecordingImportError(RecordingError):
    """A ROS bag or a line log could not be imported: it names the file, the topic or column,
    the field and what was found."""


class OutputError(CalstationError):
    """An output cannot be written where it was named: a folder, a device or a FIFO named as the
    file, a missing folder, a full disk. The previous file, if any, is left as it was."""


class TextError(CalstationError, ValueError):
    """Text a person typed (an operator's name, a unit serial) that cannot be stored: too long
    for its column, or holding a control character or another it may not."""


class SimulationError(CalstationError):
    """The simulated station was configured in a way it cannot simulate."""


class DriverError(CalstationError):
    """A driver could not talk to its device, or the device reported a fault."""


class DeviceTimeout(DriverError):
    """A device did not answer in time."""


class CalibrationError(CalstationError):
    """A calibration stage could not produce a trustworthy result."""


class InitialCalibrationError(CalibrationError):
    """The static target was not found or does not match the recipe geometry."""


class FineTuningError(CalibrationError):
    """A fine-tuning strategy could not run on the data it was given."""


class ObservabilityError(FineTuningError):
    """A fine-tuning ran, but its data do not determine a parameter well enough (σ too large).

    ``details`` carries the refused estimate, so that it can be stored with the failed step.
    """

    details: dict[str, object]

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.details = {}


class VerificationError(CalstationError):
    """The QA cube could not be measured."""


class PluginError(CalstationError):
    """A plugin is broken, duplicated or names an unknown hook."""


class StationError(CalstationError):
    """The station state machine was asked to do something it cannot."""


class AbortRun(CalstationError):
    """The operator (or a signal) aborted the run."""


class DatabaseError(CalstationError):
    """The run database is unreachable, out of date or inconsistent."""


class DamagedDatabase(DatabaseError):
    """The database file is not a database, or its content is damaged."""


class ResultJournalled(DatabaseError):
    """A result could not be written to the database and was kept in the run folder's journal."""


class FleetError(CalstationError):
    """A re-processing campaign cannot go on (its cluster, its selection, its options)."""
