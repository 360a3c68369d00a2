"""The live view: a Foxglove WebSocket client sees a simulated scan while it is taken."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calstation.recipes import load_recipe
from calstation.recordings import writer
from calstation.recordings.channels import channel_schema
from calstation.recordings.messages import decode_frame_transform, decode_laser_scan

DATA = Path(__file__).parent / "data" / "v1"
# the Foxglove WebSocket protocol: foxglove-sdk 0.30 speaks it as "foxglove.sdk.v1", the
# successor of "foxglove.websocket.v1" (same operations); a client offers both
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


async def _receive_scans(
    url: str, want: int, timeout_s: float, topics: tuple[str, ...] = ("/lidar/scan",)
) -> dict[str, Any]:
    """Connect as a Foxglove client, subscribe to ``topics`` when advertised, and collect
    messages until ``want`` LaserScans arrived. Returns the advertised channels and the
    payloads per topic."""
    import websockets

    deadline = time.monotonic() + timeout_s
    while True:  # the server may still be starting
        try:
            ws = await websockets.connect(url, subprotocols=SUBPROTOCOLS)  # type: ignore[arg-type]
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)
    channels: dict[int, dict[str, Any]] = {}
    subscriptions: dict[int, str] = {}
    got: dict[str, list[bytes]] = {t: [] for t in topics}
    info: dict[str, Any] = {}
    async with ws:
        assert ws.subprotocol in SUBPROTOCOLS
        while len(got["/lidar/scan"]) < want:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"only {len(got['/lidar/scan'])} scans before the timeout"
            frame = await asyncio.wait_for(ws.recv(), remaining)
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    info = msg
                elif msg["op"] == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        channels[ch["id"]] = ch
                        if ch["topic"] in topics:
                            sub_id = len(subscriptions) + 1
                            subscriptions[sub_id] = ch["topic"]
                            new.append({"id": sub_id, "channelId": ch["id"]})
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif frame[0] == 0x01:  # MessageData: opcode, subscription id, log time, payload
                sub_id, _ = struct.unpack_from("<IQ", frame, 1)
                got[subscriptions[sub_id]].append(bytes(frame[13:]))
    return {"info": info, "channels": list(channels.values()), "messages": got}


def _check_scans(result: dict[str, Any], points_per_line: int) -> None:
    scan_channel = next(c for c in result["channels"] if c["topic"] == "/lidar/scan")
    assert scan_channel["schemaName"] == "foxglove.LaserScan"
    assert scan_channel["encoding"] == "protobuf"
    for payload in result["messages"]["/lidar/scan"]:
        scan = decode_laser_scan(payload)
        assert scan.timestamp_ns > 0
        ranges = np.frombuffer(scan.ranges, "<f8")
        assert len(ranges) == points_per_line
        assert np.isfinite(ranges).sum() > points_per_line // 2  # the scene is seen
        assert b"lidar" in payload  # frame_id


def test_live_view_streams_a_simulated_scan(tmp_path: Path) -> None:
    """In process: a client subscribed during ``simulate_run`` receives its LaserScans, and the
    platter angle and the calibration as transforms."""
    from calstation_sim import simulate_run

    from calstation.recordings.liveview import start_live_view

    view = start_live_view(port=0)
    try:
        assert writer.live_sink() is view
        # let the client connect and subscribe first: the sim is faster than real time
        started = threading.Event()
        done: list[BaseException | None] = []

        def scan() -> None:
            started.wait(30)
            try:
                simulate_run(load_recipe(DATA / "recipe.yaml"), tmp_path, progress=False)
                done.append(None)
            except BaseException as exc:  # reported by the main thread
                done.append(exc)

        worker = threading.Thread(target=scan)
        worker.start()

        async def client() -> dict[str, Any]:
            task = asyncio.ensure_future(
                _receive_scans(view.url, 20, 60, ("/lidar/scan", "/tf", "/tf_static"))
            )
            await asyncio.sleep(1.0)  # connected and subscribed to the first channels
            started.set()
            return await task

        result = asyncio.run(client())
        worker.join(120)
        assert done == [None]
    finally:
        view.close()
    assert writer.live_sink() is None
    _check_scans(result, 250)
    tfs = [decode_frame_transform(m) for m in result["messages"]["/tf"]]
    assert tfs and {(t.parent, t.child) for t in tfs} == {("platform", "platter")}
    static = [decode_frame_transform(m) for m in result["messages"]["/tf_static"]]
    assert static and static[0].parent == "lidar" and static[0].child == "platform"
    truth = json.loads((tmp_path / "truth.json").read_text())
    np.testing.assert_allclose(static[0].translation, [truth["tx"], truth["ty"], truth["tz"]])
    # the schema a client gets is the FileDescriptorSet of the recording
    scan_channel = next(c for c in result["channels"] if c["topic"] == "/lidar/scan")
    assert base64.b64decode(scan_channel["schema"]) == (
        channel_schema("/lidar/scan").data
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_run_foxglove_option_streams_laserscans(tmp_path: Path) -> None:
    """``calstation run --foxglove PORT``: a WebSocket client connects during the simulated
    run's static scan and receives LaserScan messages."""
    port = _free_port()
    env = {**os.environ, "CALSTATION_HOME": str(tmp_path), "CALSTATION_OPERATOR": "test"}
    proc = subprocess.Popen(
        [str(Path(sys.executable).parent / "calstation"), "run", str(DATA / "recipe.yaml"), "--yes",
         "--foxglove", str(port)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    try:
        result = asyncio.run(_receive_scans(f"ws://127.0.0.1:{port}", 5, 90))
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    assert result["info"]["name"] == "calstation"
    _check_scans(result, 250)
    assert "live view: open ws://127.0.0.1:" in err


def test_port_in_use_is_a_clear_error() -> None:
    from calstation.recordings.liveview import LiveViewError, start_live_view

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(LiveViewError, match=f"cannot start the live view on 127.0.0.1:{port}"):
            start_live_view(port=port)
    assert writer.live_sink() is None


def test_foxglove_port_is_optional_on_the_command_line() -> None:
    from calstation.cli import optional_port

    assert optional_port(["run", "r.yaml", "--foxglove"]) == ["run", "r.yaml", "--foxglove", "8765"]
    assert optional_port(["run", "--foxglove", "r.yaml"]) == ["run", "--foxglove", "8765", "r.yaml"]
    assert optional_port(["run", "--foxglove", "9000", "r.yaml"]) == [
        "run", "--foxglove", "9000", "r.yaml"]
    assert optional_port(["run", "r.yaml"]) == ["run", "r.yaml"]
