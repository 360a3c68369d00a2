"""The web station's defences against a real ``calstation serve`` on 127.0.0.1: floods of event
streams, a 200 MB body, the headers uvicorn itself would add, TLS, and the command's checks of
its options.

Every server here listens on 127.0.0.1, but one on this computer's own network address (for a
station off localhost); every request loop is bounded in count and time.
The figures are also printed by ``benchmarks/web_load.py``.
"""

from __future__ import annotations

import asyncio
import importlib.util
import shutil
import socket
import ssl
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import httpx
import pytest

REPO = Path(__file__).resolve().parents[2]
TOKEN = "station-token-0123456789"


def _load_bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("web_load", REPO / "benchmarks" / "web_load.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["web_load"] = module
    spec.loader.exec_module(module)
    return module


load = _load_bench()


@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory) -> Iterator[object]:
    with load.serve(tmp_path_factory.mktemp("serve")) as s:
        yield s


def test_500_idle_event_streams_leave_a_new_client_its_first_event_within_a_second(
    station: object,
) -> None:
    """With one thread per stream, 100 idle streams made a new client wait 15 s, 300 made it
    wait 49 s. Now a stream is an async wait: the 500 streams add less than a second to what a
    new client waits without them, measured in the same minute (so on a loaded machine too)."""
    port = station.port  # type: ignore[attr-defined]

    async def main() -> tuple[list[float], list[float]]:
        alone = [await load.first_event_s(port, timeout=600) for _ in range(3)]
        alone += [(await load.get_s(port, "/state.json", timeout=600))[1] for _ in range(3)]
        writers = await load.open_streams(port, 500, timeout=600)
        try:
            assert len(writers) == 500
            await asyncio.sleep(load.IDLE_S)  # idle: every stream waits for a change
            firsts = [await load.first_event_s(port, timeout=600) for _ in range(3)]
            gets = [(await load.get_s(port, "/state.json", timeout=600))[1] for _ in range(3)]
        finally:
            for w in writers:
                w.close()
        return alone, firsts + gets

    alone, loaded = asyncio.run(main())
    print(f"500 idle streams: first event and GET /state.json {max(loaded) * 1000:.1f} ms, "
          f"{max(alone) * 1000:.1f} ms without them (worst of 6)")
    assert min(loaded) < min(alone) + 1.0


def test_a_200_mb_body_is_refused_without_the_server_growing(station: object) -> None:
    """A 200 MB JSON body was parsed, growing the server by 0.5 GB."""
    port, pid = station.port, station.process.pid  # type: ignore[attr-defined]
    for chunked in (False, True):
        before = load.memory_mib(pid)
        outcome, seconds = asyncio.run(load.post_body(port, 200 << 20, chunked=chunked))
        after = load.memory_mib(pid)
        print(f"200 MB ({'chunked' if chunked else 'Content-Length'}): {outcome} in "
              f"{seconds:.2f} s, peak memory {before['VmHWM']:.0f} → {after['VmHWM']:.0f} MiB")
        assert " 413 " in outcome  # refused; not read to its end: the memory says so
        assert after["VmHWM"] - before["VmHWM"] < 30
        status, _ = asyncio.run(load.get_s(port, "/state.json", timeout=600))
        assert status == 200
    log = station.log.read_text()  # type: ignore[attr-defined]
    assert "refused POST /api/start from 127.0.0.1: 413 request body of 209715200 bytes" in log
    assert "refused POST /api/start from 127.0.0.1: 413 request body larger than 65536" in log


def _raw(port: int, request: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(request)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
            if len(data) > 1 << 20:
                break
    return data


def test_the_real_server_sends_the_headers_and_no_banner(station: object) -> None:
    url, port = station.url, station.port  # type: ignore[attr-defined]
    r = httpx.get(url + "/", timeout=10)
    assert r.status_code == 200 and "server" not in r.headers
    assert "frame-ancestors 'none'" in r.headers["content-security-policy"]
    assert r.headers["x-content-type-options"] == "nosniff"
    assert r.headers["referrer-policy"] == "no-referrer"
    r = httpx.get(url + "/state.json", headers={"Host": "evil.test"}, timeout=10)
    assert r.status_code == 400 and "not a name of this station" in r.text
    assert "server" not in r.headers
    # HTTP/1.0 has no Host: refused
    head = _raw(port, b"GET /state.json HTTP/1.0\r\n\r\n").split(b"\r\n\r\n")[0]
    assert head.startswith(b"HTTP/1.1 400") and b"server:" not in head.lower()
    # a websocket upgrade: the station has none
    head = _raw(port, b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
                      b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                      b"Sec-WebSocket-Version: 13\r\n\r\n")
    assert not head.startswith(b"HTTP/1.1 101")


def test_forwarded_headers_neither_change_the_client_nor_escape_the_back_off(
    tmp_path: Path,
) -> None:
    """uvicorn takes ``X-Forwarded-For`` / ``-Proto`` from 127.0.0.1 by default: a process of
    this computer could have guessed tokens without end, one made-up address per try, and had
    the log name an address of its choosing. The station is served without a proxy."""
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    with load.serve(tmp_path, "--token-file", str(token_file)) as s:
        codes = []
        for k in range(8):
            r = httpx.post(s.url + "/api/abort", timeout=10, headers={
                "Authorization": "Bearer wrong-token-0123456789",
                "X-Forwarded-For": f"10.9.9.{k}", "X-Real-IP": f"10.9.8.{k}",
                "Forwarded": f"for=10.9.7.{k}"})
            codes.append(r.status_code)
        # 5 wrong tokens free, the 6th locks 127.0.0.1 out, whatever address each claims
        assert codes[:6] == [401] * 6 and 429 in codes[6:], codes
        log = s.log.read_text()  # type: ignore[union-attr]
        assert "refused POST /api/abort from 127.0.0.1: 429 too many wrong tokens" in log
        assert "10.9." not in log
    # X-Forwarded-Proto does not make the station's origin https
    with load.serve(tmp_path / "plain") as s, httpx.Client(base_url=s.url, timeout=10) as web:
        csrf = web.get("/").text.split('name="csrf-token" content="')[1].split('"')[0]
        https = s.url.replace("http://", "https://")
        r = web.post("/api/abort", headers={"X-CSRF-Token": csrf, "Origin": https,
                                            "X-Forwarded-Proto": "https"})
        assert r.status_code == 403 and "cross-site request" in r.text
        r = web.post("/api/abort", headers={"X-CSRF-Token": csrf, "Origin": s.url,
                                            "X-Forwarded-Proto": "https"})
        assert r.status_code == 409  # the station's own origin; nothing runs


def _network_address() -> str | None:
    """This computer's address on its network (None without one): a UDP socket's source
    address towards a documentation address; no packet is sent."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))
            address = str(probe.getsockname()[0])
    except OSError:
        return None
    return None if address.startswith("127.") or address == "0.0.0.0" else address


def test_off_localhost_a_stream_needs_the_session_and_a_client_opens_at_most_eight(
    tmp_path: Path,
) -> None:
    """Served on a network address (with its token), the event stream needs the logged-in
    session or the token, and one client address opens at most 8 streams."""
    address = _network_address()
    if address is None:
        pytest.skip("this computer has no network address to serve on")
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    with load.serve(tmp_path, "--token-file", str(token_file), host=address) as s:
        origin = f"http://{address}:{s.port}"

        def stream(extra: str = "") -> tuple[socket.socket, bytes]:
            conn = socket.create_connection((address, s.port), timeout=10)
            conn.sendall(f"GET /events HTTP/1.1\r\nHost: {address}:{s.port}\r\n{extra}\r\n"
                         .encode())
            return conn, conn.recv(200).split(b"\r\n")[0]

        conn, status = stream()
        conn.close()
        assert status == b"HTTP/1.1 401 Unauthorized"
        with httpx.Client(base_url=origin, timeout=10) as web:
            csrf = web.get("/").text.split('name="csrf-token" content="')[1].split('"')[0]
            r = web.post("/login", data={"token": TOKEN, "csrf": csrf},
                         headers={"Origin": origin})
            assert r.status_code == 303
            cookie = f"Cookie: {'; '.join(f'{k}={v}' for k, v in web.cookies.items())}\r\n"
        opened = [stream(cookie) for _ in range(10)]
        try:
            assert [st for _, st in opened] == [b"HTTP/1.1 200 OK"] * 8 + [
                b"HTTP/1.1 429 Too Many Requests"] * 2
        finally:
            for conn, _ in opened:
                conn.close()
        log = s.log.read_text()  # type: ignore[union-attr]
        assert f"refused GET /events from {address}: 401 this station needs its token" in log
        assert f"refused GET /events from {address}: 429 {address} has 8 event streams" in log


@pytest.fixture(scope="module")
def certificate(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make a test certificate")
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
                    "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
                    "-keyout", str(key), "-out", str(cert)],
                   check=True, capture_output=True, timeout=60)
    return cert, key


def test_tls_with_a_certificate_and_key_from_the_command_line(
    tmp_path: Path, certificate: tuple[Path, Path]
) -> None:
    cert, key = certificate
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    with load.serve(tmp_path, "--tls-cert", str(cert), "--tls-key", str(key),
                    "--token-file", str(token_file)) as s:
        verify = ssl.create_default_context(cafile=str(cert))
        origin = s.url
        assert origin.startswith("https://127.0.0.1:")
        with httpx.Client(base_url=origin, verify=verify, timeout=10) as client:
            r = client.get("/")
            assert r.status_code == 200
            assert r.headers["strict-transport-security"].startswith("max-age=")
            cookie = r.headers["set-cookie"]
            # a secure, host-only cookie that no plain-HTTP page of this host can overwrite
            assert cookie.startswith("__Host-calstation_session=")
            attrs = {a.strip().lower() for a in cookie.split(";")[1:]}
            assert {"secure", "httponly", "samesite=strict", "path=/"} <= attrs
            csrf = r.text.split('name="csrf-token" content="')[1].split('"')[0]
            r = client.post("/login", data={"token": TOKEN, "csrf": csrf},
                            headers={"Origin": origin})
            assert r.status_code == 303, r.text
            assert "secure" in r.headers["set-cookie"].lower()
            csrf = client.get("/").text.split('name="csrf-token" content="')[1].split('"')[0]
            r = client.post("/api/abort", headers={"X-CSRF-Token": csrf, "Origin": origin})
            assert r.status_code == 409  # logged in; nothing runs
            # the http origin of the same host is another origin
            r = client.post("/api/abort", headers={"X-CSRF-Token": csrf,
                                                   "Origin": origin.replace("https", "http")})
            assert r.status_code == 403
        # plain HTTP is not served on the TLS port
        with pytest.raises(httpx.HTTPError):
            httpx.get(origin.replace("https", "http") + "/state.json", timeout=5)


def test_serve_checks_its_security_options(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from tests.support.clirun import run_cli

    monkeypatch.delenv("CALSTATION_TOKEN", raising=False)
    base = ["serve", "--port", "1", "--db", f"sqlite:///{tmp_path / 'x.db'}"]
    code, _, err = run_cli([*base, "--tls-cert", str(tmp_path / "c.pem")], capsys)
    assert code == 2 and "--tls-cert and --tls-key go together" in err
    code, _, err = run_cli([*base, "--allow-host", "evil.test/path"], capsys)
    assert code == 2 and "is not a host name" in err
    short = tmp_path / "token"
    short.write_text("short\n")
    code, _, err = run_cli([*base, "--token-file", str(short)], capsys)
    assert code == 2 and "too short" in err
    short.write_text("spaces in the token\n")
    code, _, err = run_cli([*base, "--token-file", str(short)], capsys)
    assert code == 2 and "printable ASCII without spaces" in err
