"""``settings`` of the ``canopen402`` and ``canopen406`` drivers: a light module, so that a
recipe's driver settings are checked (``calstation recipes validate``) without importing
python-can, and registering the drivers imports neither it nor pydantic."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Settings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    interface: str = Field("socketcan", min_length=1)
    channel: str | int | None = None
    bitrate: int = Field(500_000, ge=10_000, le=1_000_000)
    sdo_timeout_s: float = Field(0.5, gt=0, le=60)
    emulate: bool = False


class Cia402Settings(_Settings):
    """``settings`` of ``canopen402`` (defaults: :data:`calstation_canopen.drive.
    SETTINGS_DEFAULTS`); checked by ``calstation recipes validate``."""

    node_id: int = Field(1, ge=1, le=127, description="CANopen node id of the drive")
    master_id: int = Field(127, ge=1, le=127)
    velocity_unit_rpm: float = Field(0.01, gt=0, le=1000)
    counts_per_revolution: int = Field(10_000, ge=1, le=2**31 - 1)
    direction: Literal[1, -1] = 1
    sync_period_s: float = Field(0.01, ge=0.0005, le=10)
    heartbeat_period_s: float = Field(0.1, ge=0.001, le=60)
    heartbeat_timeout_s: float = Field(0.5, ge=0.001, le=60)
    master_heartbeat_s: float = Field(0.1, ge=0.001, le=60)
    state_timeout_s: float = Field(1.0, gt=0, le=60)
    stop_timeout_s: float = Field(15.0, gt=0, le=600)
    stop_tolerance_rpm: float = Field(0.05, gt=0, le=100)
    move_rpm: float = Field(2.0, gt=0, le=120)
    move_tolerance_rad: float = Field(0.002, gt=0, le=1)


class Cia406Settings(_Settings):
    """``settings`` of ``canopen406`` (defaults: :data:`calstation_canopen.encoder.
    SETTINGS_DEFAULTS`); checked by ``calstation recipes validate``."""

    node_id: int = Field(2, ge=1, le=127, description="CANopen node id of the encoder")
    mode: Literal["sync", "cyclic"] = "sync"
    sync_period_s: float = Field(0.002, ge=0.0005, le=10)
    cyclic_ms: int = Field(2, ge=1, le=65_535)
    counts_per_revolution: int | None = Field(None, ge=1, le=2**31 - 1)
    latency_s: float = Field(0.0, ge=-1, le=1)
