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

DATA = Path(__file__).resolve().parents[1] / "data" / "v1"
# the Foxglove WebSocket protocol goes by two names: "foxglove.sdk.v1" (current Foxglove,
# foxglove-sdk's server) and "foxglove.websocket.v1" (older Foxglove Studio and Lichtblick, which
# offer it alone); recent Lichtblick offers both. The live view serves each.
SDK = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"


async def _connect(url: str, subprotocols: list[str], timeout_s: float) -> Any:
    import websockets

    deadline = time.monotonic() + timeout_s
    while True:  # the server may still be starting
        try:
            return await websockets.connect(url, subprotocols=subprotocols)  # type: ignore[arg-type]
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


async def _receive_scans(
    url: str, want: int, timeout_s: float, topics: tuple[str, ...] = ("/lidar/scan",),
    subprotocols: tuple[str, ...] = (SDK,),
) -> dict[str, Any]:
    """Connect as a Foxglove client offering ``subprotocols``, subscribe to ``topics`` when
    advertised, and collect messages until ``want`` LaserScans arrived. Returns the advertised
    channels, the payloads per topic and their log times."""
    deadline = time.monotonic() + timeout_s
    ws = await _connect(url, list(subprotocols), timeout_s)
    channels: dict[int, dict[str, Any]] = {}
    subscriptions: dict[int, str] = {}
    got: dict[str, list[bytes]] = {t: [] for t in topics}
    log_times: dict[str, list[int]] = {t: [] for t in topics}
    info: dict[str, Any] = {}
    async with ws:
        assert ws.subprotocol == (SDK if SDK in subprotocols else LEGACY)
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
                sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                got[subscriptions[sub_id]].append(bytes(frame[13:]))
                log_times[subscriptions[sub_id]].append(log_time)
    return {"info": info, "channels": list(channels.values()), "messages": got,
            "log_times": log_times}


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
    platter angle and the calibration as transforms, all stamped on the simulated clock. The
    client offers only the older subprotocol name, as Foxglove Studio and Lichtblick did."""
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
                _receive_scans(view.url, 20, 60, ("/lidar/scan", "/tf", "/tf_static"),
                               subprotocols=(LEGACY,))
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
    # one clock: every message the client got is stamped within the simulated run's time, the
    # calibration no later than the first scan
    from calstation.recordings.reader import read_recording

    recs = [read_recording(tmp_path / f"{k}.mcap") for k in ("static", "spin", "cube")]
    start = min(int(r.metadata["calstation"]["created_ns"]) for r in recs)
    end = max(int(max(r.t_ns.max(), r.encoder_t_ns.max())) for r in recs)
    for topic, times in result["log_times"].items():
        assert times and all(start <= t <= end for t in times), topic
    assert min(result["log_times"]["/tf_static"]) <= min(result["log_times"]["/lidar/scan"])
    static = [decode_frame_transform(m) for m in result["messages"]["/tf_static"]]
    assert static and static[0].parent == "lidar" and static[0].child == "platform"
    truth = json.loads((tmp_path / "truth.json").read_text())
    np.testing.assert_allclose(static[0].translation, [truth["tx"], truth["ty"], truth["tz"]])
    # the schema a client gets is the FileDescriptorSet of the recording
    scan_channel = next(c for c in result["channels"] if c["topic"] == "/lidar/scan")
    assert base64.b64decode(scan_channel["schema"]) == (
        channel_schema("/lidar/scan").data
    )


@pytest.mark.parametrize(
    "offered", [[SDK], [LEGACY], [SDK, LEGACY], [LEGACY, SDK]],
    ids=["sdk", "legacy", "both", "legacy-first"],
)
def test_clients_of_either_subprotocol_are_served(offered: list[str]) -> None:
    """Current Foxglove offers foxglove.sdk.v1, older Foxglove Studio and Lichtblick
    foxglove.websocket.v1 alone, recent Lichtblick both: each is answered with a name it offered,
    gets the channels, and receives what a writer publishes."""
    from calstation.recordings.channels import STATIC_TF_TOPIC
    from calstation.recordings.liveview import start_live_view
    from calstation.recordings.messages import frame_transform

    view = start_live_view(port=0)
    try:
        async def client() -> tuple[str | None, list[str], int, bytes]:
            ws = await _connect(view.url, offered, 10)
            async with ws:
                topics: dict[int, str] = {}
                while "/tf_static" not in topics.values():
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
                    if msg["op"] == "advertise":
                        topics.update({c["id"]: c["topic"] for c in msg["channels"]})
                cid = next(i for i, t in topics.items() if t == "/tf_static")
                await ws.send(json.dumps({"op": "subscribe",
                                          "subscriptions": [{"id": 7, "channelId": cid}]}))
                await asyncio.sleep(0.3)  # subscribed
                data = frame_transform(123, "lidar", "platform", [0, 1, 0], [0, 0, 0, 1])
                view.publish(STATIC_TF_TOPIC, channel_schema(STATIC_TF_TOPIC), data, 123)
                while True:
                    frame = await asyncio.wait_for(ws.recv(), 10)
                    if isinstance(frame, bytes) and frame[0] == 0x01:
                        sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                        assert sub_id == 7
                        return ws.subprotocol, sorted(topics.values()), log_time, frame[13:]

        subprotocol, topics, log_time, payload = asyncio.run(client())
    finally:
        view.close()
    assert subprotocol == (SDK if SDK in offered else LEGACY)
    assert "/lidar/scan" in topics and "/tf_static" in topics
    assert log_time == 123
    assert decode_frame_transform(payload).child == "platform"


def test_a_client_of_another_protocol_is_refused() -> None:
    from websockets.exceptions import InvalidStatus

    from calstation.recordings.liveview import start_live_view

    view = start_live_view(port=0)
    try:
        with pytest.raises(InvalidStatus, match="400"):
            asyncio.run(_connect(view.url, ["something.else.v1"], 5))
    finally:
        view.close()


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
