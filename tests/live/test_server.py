"""The live web server: token, Host and Origin rules, captures (path safety, atomic writes), port errors, packets."""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("httpx")
import warnings  # noqa: E402

with warnings.catch_warnings():  # starlette >= 1.x asks for httpx2; httpx works the same for these tests
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient
from starlette.websockets import WebSocketDisconnect  # noqa: E402

from pihim.camera.frames import read_frame  # noqa: E402
from pihim.cli import main  # noqa: E402
from pihim.errors import PihimInputError  # noqa: E402
from pihim.live.engine import LiveConfig, LiveEngine, unpack_packet  # noqa: E402
from pihim.live.exposure import ExposureSettings  # noqa: E402
from pihim.live.server import bind_socket, build_app, check_bind  # noqa: E402
from pihim.live.sources import SyntheticSource  # noqa: E402

jsonschema = pytest.importorskip("jsonschema")
pytestmark = pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")
SCHEMAS = {name: json.loads(resources.files("pihim").joinpath(f"schemas/{name}.schema.json").read_text())
           for name in ("live-capture", "live-frame", "live-session")}
TOKEN = "t0ken-for-the-tests-0123456789"


@pytest.fixture
def engine(tmp_path):
    src = SyntheticSource((64, 80), fps=60.0, scenes=1, drift_px=4)
    return LiveEngine(src, LiveConfig(capture_dir=tmp_path / "captures", preview_max_side=64))


def _wait_frame(client: TestClient, headers=None, params=None) -> None:
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if client.get("/api/status", headers=headers, params=params).json()["seq"] > 0:
            return
        time.sleep(0.05)
    raise AssertionError("no frame within 20 s")


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


# --------------------------------------------------------------------------- binding rules


def test_check_bind_requires_a_token_off_loopback():
    check_bind("127.0.0.1", None)
    check_bind("localhost", None)
    check_bind("::1", None)
    with pytest.raises(PihimInputError, match="--host 0.0.0.0 .* --token"):
        check_bind("0.0.0.0", None)
    with pytest.raises(PihimInputError, match="--token"):
        check_bind("192.168.1.20", None)
    with pytest.raises(PihimInputError, match="at least 16"):
        check_bind("0.0.0.0", "short")
    check_bind("0.0.0.0", TOKEN)


def test_port_in_use_is_one_line_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(PihimInputError, match=f"--port {port}: 127.0.0.1:{port} is already in use"):
            bind_socket("127.0.0.1", port)
    with pytest.raises(PihimInputError, match="--port"):
        bind_socket("127.0.0.1", 70000)


def test_cli_port_in_use_and_bad_input_exit_2(tmp_path, capsys, frame_folder):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["live", "--source", str(frame_folder), "--port", str(port),
                     "--captures", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already in use" in err and "Traceback" not in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["live", "--source", str(empty), "--port", "0", "--captures", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no frames in the folder" in err
    assert main(["live", "--source", "synthetic", "--host", "0.0.0.0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--token" in err


# --------------------------------------------------------------------------- access rules


def test_token_required_on_every_route(engine):
    app = build_app(engine, token=TOKEN)
    with TestClient(app, base_url="http://192.168.1.20:8765") as client:
        assert client.get("/").status_code == 401
        assert client.get("/", params={"token": "x" * 30}).status_code == 401
        assert client.get("/api/status").status_code == 401
        assert client.post("/api/capture", json={}).status_code == 401
        with pytest.raises(WebSocketDisconnect), client.websocket_connect("/ws") as ws:
            ws.receive()
        r = client.get("/", params={"token": TOKEN})
        assert r.status_code == 200 and "pihim live" in r.text
        assert r.headers["content-security-policy"].startswith("default-src 'self'")
        # any Host is fine with a token: the server was bound for other machines on purpose
        assert client.get("/api/status", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
        _wait_frame(client, headers={"Authorization": f"Bearer {TOKEN}"})
        with client.websocket_connect(f"/ws?token={TOKEN}") as ws:
            msg = ws.receive()
            assert msg.get("bytes") or msg.get("text")


def test_localhost_only_host_header_and_origin(engine):
    app = build_app(engine)
    with TestClient(app, base_url="http://127.0.0.1:8765") as client:
        assert client.get("/").status_code == 200
        assert client.get("/", headers={"Host": "localhost:8765"}).status_code == 200
        # DNS rebinding: a foreign name resolving to 127.0.0.1 is refused
        assert client.get("/", headers={"Host": "attacker.example:8765"}).status_code == 403
        # a page of another origin cannot capture or open the frame stream
        r = client.post("/api/capture", json={}, headers={"Origin": "http://attacker.example"})
        assert r.status_code == 403
        with pytest.raises(WebSocketDisconnect) as info, client.websocket_connect(
                "/ws", headers={"Host": "127.0.0.1:8765", "Origin": "http://attacker.example"}) as ws:
            ws.receive()
        assert "cross-origin" in info.value.reason
        with client.websocket_connect("/ws", headers={"Host": "127.0.0.1:8765",
                                                      "Origin": "http://127.0.0.1:8765"}) as ws:
            assert ws.receive()["type"] == "websocket.send"
        # the page's own origin is fine
        _wait_frame(client)
        r = client.post("/api/capture", json={}, headers={"Origin": "http://127.0.0.1:8765"})
        assert r.status_code == 200


# --------------------------------------------------------------------------- captures


@pytest.mark.parametrize("body", [
    {"label": "../../escape"}, {"label": "a/b"}, {"label": "/etc/passwd"}, {"label": "..\\x"}, {"label": ".hidden"},
    {"label": "x" * 49}, {"label": "nul\x00byte"}, {"label": 5}, {"label": ["a"]}, {"path": "/tmp/x"},
    {"label": "ok", "dir": ".."}, ["label"],
])
def test_capture_refuses_unsafe_requests(engine, tmp_path, body):
    app = build_app(engine)
    before = _files(tmp_path)
    with TestClient(app, base_url="http://127.0.0.1:8765") as client:
        _wait_frame(client)
        r = client.post("/api/capture", json=body)
        assert r.status_code == 400, r.text
    after = _files(tmp_path)
    assert after - before <= {"captures"}  # nothing written anywhere, not even in the capture folder
    assert not list((tmp_path / "captures").glob("*")) if (tmp_path / "captures").exists() else True


def test_capture_needs_json_content_type(engine):
    with TestClient(build_app(engine), base_url="http://127.0.0.1:8765") as client:
        _wait_frame(client)
        r = client.post("/api/capture", content=b"label=x", headers={"Content-Type": "text/plain"})
        assert r.status_code == 415


def test_capture_writes_raw_and_json(engine, tmp_path):
    cap = tmp_path / "captures"
    with TestClient(build_app(engine), base_url="http://127.0.0.1:8765") as client:
        _wait_frame(client)
        r = client.post("/api/capture", json={"label": "pass-3_A"})
        assert r.status_code == 200, r.text
        rec = r.json()
    assert rec["raw_file"].endswith("-pass-3_A.tiff")
    names = sorted(p.name for p in cap.iterdir())
    assert names == sorted([rec["raw_file"], rec["json_file"]])  # no temporaries left
    raw = read_frame(cap / rec["raw_file"])
    assert raw.data.shape == (64, 80) and raw.data.dtype == np.uint16
    doc = json.loads((cap / rec["json_file"]).read_text())
    jsonschema.validate(doc, SCHEMAS["live-capture"])
    assert doc["raw_sha256"] == hashlib.sha256((cap / rec["raw_file"]).read_bytes()).hexdigest()
    assert doc["raw_bytes"] == os.path.getsize(cap / rec["raw_file"])
    assert doc["exposure"]["exposure_us"] > 0 and doc["source"]["kind"] == "synthetic"
    # the raw data are a real frame of the scene: the level follows the recorded exposure
    assert 0 < np.median(raw.data) < 4095


def test_capture_is_never_half_written(engine, tmp_path, monkeypatch):
    import tifffile

    def failing_write(path, data, **kwargs):
        Path(path).write_bytes(b"II*\0partial")
        raise OSError(28, "No space left on device")

    cap = tmp_path / "captures"
    with TestClient(build_app(engine), base_url="http://127.0.0.1:8765") as client:
        _wait_frame(client)
        monkeypatch.setattr(tifffile, "imwrite", failing_write)
        r = client.post("/api/capture", json={})
        assert r.status_code == 500 and "No space left" in r.json()["error"]
    assert list(cap.iterdir()) == []  # neither the TIFF, nor its temporary, nor a JSON


# --------------------------------------------------------------------------- frames on the WebSocket


def test_websocket_packets(engine):
    import cv2

    with TestClient(build_app(engine), base_url="http://127.0.0.1:8765") as client:
        _wait_frame(client)
        got = None
        with client.websocket_connect("/ws", headers={"Host": "127.0.0.1:8765"}) as ws:
            for _ in range(20):
                msg = ws.receive()
                if msg.get("bytes"):
                    got = msg["bytes"]
                    break
        assert got is not None
    header, images = unpack_packet(got)
    jsonschema.validate(header, SCHEMAS["live-frame"])
    assert set(images) == {"s0", "dolp", "aop"}
    assert header["region"] == "source" and header["exposure"]["exposure_us"] > 0
    for name, data in images.items():
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img.shape[:2] == (header["preview"]["height"], header["preview"]["width"])
        assert img.ndim == (2 if name == "s0" else 3)
    assert engine.status()["latency_ms"]["n"] >= 1


def _first_header(eng: LiveEngine) -> dict:
    eng.start()
    try:
        deadline = time.monotonic() + 20
        while eng.latest()[1] is None and time.monotonic() < deadline:
            time.sleep(0.02)
        packet = eng.latest()[1]
    finally:
        eng.stop()
    assert packet is not None
    header, _ = unpack_packet(packet)
    jsonschema.validate(header, SCHEMAS["live-frame"])
    return header


def test_a_fixed_exposure_is_set_without_the_controller(tmp_path):
    """``--no-auto-exposure --exposure-us 5000``: after the camera's actuation latency (2 frames) every frame is
    taken at 5000 us, not at the camera's own 1000 us."""
    src = SyntheticSource((64, 80), fps=60.0, scenes=1, drift_px=4, latency_frames=2)
    assert src.describe()["controllable"]
    headers = []
    eng = LiveEngine(src, LiveConfig(exposure=None, initial_settings=ExposureSettings(5000.0),
                                     capture_dir=tmp_path / "captures", preview_max_side=64),
                     on_packet=lambda: (p := eng.latest()[1]) is not None and headers.append(unpack_packet(p)[0]))
    eng.start()
    try:
        deadline = time.monotonic() + 20
        while len(headers) < 12 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        eng.stop()
    seen = [h["exposure"]["exposure_us"] for h in headers[:12]]
    assert len(seen) == 12 and all(h["controller"] is None for h in headers)
    assert seen[3:] == [5000.0] * 9 and set(seen[:3]) <= {1000.0, 5000.0}


def test_saturated_mirrors_have_no_dolp(tmp_path):
    """All mirror pixels clipped (100x too bright, no exposure control): no DoLP figure, not a number from clipped pixels."""
    src = SyntheticSource((64, 80), fps=60.0, scenes=1, drift_px=4, brightness=(100.0,))
    header = _first_header(LiveEngine(src, LiveConfig(exposure=None, capture_dir=tmp_path / "captures",
                                                      preview_max_side=64)))
    assert header["region"] == "source" and header["region_stats"]["fraction_saturated"] == 1.0
    assert header["dolp_mirrors"] is None and header["dolp_usable"] is None


def test_cli_session_json(tmp_path, capsys):
    rc = main(["live", "--source", "synthetic", "--size", "64x48", "--port", "0", "--duration", "2",
               "--captures", str(tmp_path / "c"), "--record", str(tmp_path / "rec"), "--json"])
    assert rc == 0
    out = capsys.readouterr().out.strip().splitlines()
    doc = json.loads(out[-1])
    jsonschema.validate(doc, SCHEMAS["live-session"])
    assert doc["frames"] > 0 and doc["stopped_by"] == "duration"
    # --record wrote complete captures: every JSON has its TIFF
    recs = sorted((tmp_path / "rec").glob("*.json"))
    assert len(recs) == doc["recorded"] > 0
    for p in recs[:3]:
        rec = json.loads(p.read_text())
        jsonschema.validate(rec, SCHEMAS["live-capture"])
        assert (tmp_path / "rec" / rec["raw_file"]).stat().st_size == rec["raw_bytes"]
