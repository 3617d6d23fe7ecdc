"""The writer thread and MCAP helpers in-process: rotation, disk full, recovery, key matching, stamps."""

from __future__ import annotations

import errno
import io
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from services.recorder.settings import RecorderSettings
from services.recorder.writer import RecordWriter
from shared import mcaplog
from shared.bus import encode
from shared.messages import ReasoningStep, VehicleState
from tests.recorder.samples import K, frames, step_message


def settings(tmp_path: Path, **kw) -> RecorderSettings:
    return RecorderSettings(out_dir=str(tmp_path / "rec"), chunk_size=4096, **kw)


def submit_model(w: RecordWriter, key: str, obj) -> None:
    data, enc = encode(obj)
    assert w.submit(key, data, str(enc), time.time_ns())


def count_messages(path: Path) -> int:
    with path.open("rb") as f:
        return sum(1 for _ in make_reader(f).iter_messages())


def wait_for(pred, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not met"
        time.sleep(0.01)


def test_rotation_by_size_keeps_every_message_across_finished_files(tmp_path: Path) -> None:
    w = RecordWriter(settings(tmp_path, rotate_mb=0.005))
    w.start()
    for i in range(400):
        submit_model(w, K.autopilot_state, VehicleState(message=f"#{i}" * 10))
    w.stop()
    files = sorted((tmp_path / "rec").glob("*.mcap"))
    assert len(files) >= 3, files
    assert sum(count_messages(f) for f in files) == 400
    for f in files:  # every file is finished and carries the metadata records
        assert mcaplog.salvage(f).complete
        assert {"aermani", "aermani.session"} <= set(mcaplog.metadata(f))
    texts = [VehicleState.model_validate_json(s.payload).message for f in files for s in mcaplog.iter_samples(f)]
    assert texts == [f"#{i}" * 10 for i in range(400)]


def test_rotation_by_time(tmp_path: Path) -> None:
    w = RecordWriter(settings(tmp_path, rotate_s=0.3))
    w.start()
    submit_model(w, K.autopilot_state, VehicleState())
    wait_for(lambda: len(w.files) >= 2)
    submit_model(w, K.autopilot_state, VehicleState())
    w.stop()
    files = sorted((tmp_path / "rec").glob("*.mcap"))
    assert len(files) >= 2
    assert sum(count_messages(f) for f in files) == 2


class FullDisk(io.RawIOBase):
    """A file that accepts `room` bytes, then fails with ENOSPC like a full disk."""

    def __init__(self, room: int) -> None:
        self.room = room

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        if len(b) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(b)
        return len(b)


def test_disk_full_is_reported_and_the_writer_recovers(tmp_path: Path) -> None:
    disks = [FullDisk(6000)]

    def opener(path: Path):
        path.touch()
        return disks[0]

    w = RecordWriter(settings(tmp_path, retry_s=0.2), opener=opener)
    w.start()
    for i in range(100):
        submit_model(w, K.autopilot_state, VehicleState(message=f"#{i}"))
    wait_for(lambda: not w.ok)
    assert "No space left" in w.error and w.errors >= 1
    stats = w.stats()
    assert stats["lost_on_error"] > 0 and stats["error"]
    # Still full: every retry fails; none of them may leave a file behind.
    for i in range(5):
        submit_model(w, K.autopilot_state, VehicleState(message=f"still full #{i}"))
        time.sleep(0.25)
    wait_for(lambda: w.errors >= 3)
    disks[0] = FullDisk(1 << 30)  # space again
    wait_for(lambda: w.ok)  # a new file after retry_s
    submit_model(w, K.autopilot_state, VehicleState(message="after"))
    w.stop()
    assert w.ok
    on_disk = sorted((tmp_path / "rec").glob("*.mcap"))
    assert len(on_disk) == len(w.files) == 2, (w.errors, on_disk)  # one file per disk-full episode
    assert w.written + w.lost_on_error == 106


def test_a_task_event_is_on_disk_at_once_not_with_its_chunk(tmp_path: Path) -> None:
    """A reasoning step finishes the chunk in progress: a SIGKILL right after it (the file as it is on disk
    while the writer still runs) keeps the step, though the chunk size is far from reached; a state sample
    after it waits for its chunk as before."""
    w = RecordWriter(RecorderSettings(out_dir=str(tmp_path / "rec"), chunk_size=1 << 20))
    w.start()
    submit_model(w, K.autopilot_state, VehicleState(message="before"))
    submit_model(w, K.reasoning_step, step_message("t", 1, "forward"))
    submit_model(w, K.autopilot_state, VehicleState(message="after"))
    wait_for(lambda: w.written == 3)
    [path] = sorted((tmp_path / "rec").glob("*.mcap"))
    killed = tmp_path / "killed.mcap"
    killed.write_bytes(path.read_bytes())  # what a SIGKILL now would leave
    w.stop()
    assert w.durable == 3
    keys = [s.key for s in mcaplog.iter_samples(killed)]
    assert keys == [K.autopilot_state, K.reasoning_step], keys
    res = mcaplog.recover(killed, tmp_path / "fixed.mcap")
    assert res.messages == 2 and not res.complete


class ToggleDisk(io.RawIOBase):
    """A real file on a disk that is full (ENOSPC on every write) while `full[0]` is set."""

    def __init__(self, path: Path, full: list[bool]) -> None:
        self.f = open(path, "wb", buffering=0)  # noqa: SIM115 - closed by the writer
        self.full = full

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        if self.full[0]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return self.f.write(b)

    def close(self) -> None:
        self.f.close()
        super().close()


def test_task_events_outlive_a_full_disk(tmp_path: Path) -> None:
    """Steps that arrive while the disk is full (or whose chunk the full disk broke) are kept and written first
    into the file opened when space returns; state samples meanwhile are counted lost, as before."""
    full = [False]
    w = RecordWriter(settings(tmp_path, retry_s=0.2), opener=lambda path: ToggleDisk(path, full))
    w.start()
    submit_model(w, K.reasoning_step, step_message("t", 1, "forward"))
    wait_for(lambda: w.durable == 1)
    full[0] = True  # the next chunk fails, and every retry
    for i in range(2, 6):
        submit_model(w, K.autopilot_state, VehicleState(message=f"#{i}"))
        submit_model(w, K.reasoning_step, step_message("t", i, "forward"))
    wait_for(lambda: not w.ok and w.stats()["held"] == 4)
    full[0] = False  # space again
    wait_for(lambda: w.ok and w.stats()["held"] == 0)
    w.stop()
    assert w.written + w.lost_on_error == 9 and w.lost_on_error == 4, w.stats()
    steps = [ReasoningStep.model_validate_json(s.payload).step for f in w.files
             for s in mcaplog.iter_samples(f, keys=K.reasoning_step)]
    assert steps == [1, 2, 3, 4, 5], steps


def test_salvage_keeps_complete_chunks_of_a_truncated_file(tmp_path: Path) -> None:
    w = RecordWriter(settings(tmp_path))
    w.start()
    for i in range(200):
        submit_model(w, K.reasoning_step, step_message("t", i + 1, "forward"))
    w.stop()
    [path] = sorted((tmp_path / "rec").glob("*.mcap"))
    data = path.read_bytes()
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[: len(data) // 2])  # cut in the middle of a chunk
    res = mcaplog.recover(broken, tmp_path / "fixed.mcap")
    assert not res.complete and res.error
    n = count_messages(tmp_path / "fixed.mcap")
    assert 0 < n < 200 and n == res.messages
    steps = [ReasoningStep.model_validate_json(s.payload).step for s in mcaplog.iter_samples(tmp_path / "fixed.mcap")]
    assert steps == list(range(1, n + 1))
    # The unfinished file is also readable directly (sequentially, up to the last complete chunk).
    assert len(list(mcaplog.iter_samples(broken))) == n


def test_recovery_streams_with_bounded_memory(tmp_path: Path) -> None:
    """Recovering a large unfinished log holds about one chunk, not the log: the peak Python allocation stays
    far below the log's size."""
    import tracemalloc

    w = RecordWriter(RecorderSettings(out_dir=str(tmp_path / "rec"), chunk_size=256 * 1024, compression="none",
                                      queue_size=1000))
    w.start()
    blob = bytes(range(256)) * 256  # 64 KiB per message, incompressible enough
    for i in range(600):  # ~38 MiB
        while not w.submit("aermani/v1/am1/bench/blob", blob, "application/octet-stream", i + 1):
            time.sleep(0.01)
    w.stop()
    [path] = sorted((tmp_path / "rec").glob("*.mcap"))
    broken = tmp_path / "broken.mcap"
    data = path.read_bytes()
    broken.write_bytes(data[: len(data) - 100_000])
    del data
    tracemalloc.start()
    res = mcaplog.recover(broken, tmp_path / "fixed.mcap")
    _cur, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    size = broken.stat().st_size
    assert res.messages > 500 and not res.complete
    assert peak < size / 4, f"recovery peaked at {peak / 2**20:.1f} MiB for a {size / 2**20:.1f} MiB log"
    assert count_messages(tmp_path / "fixed.mcap") == res.messages


@pytest.mark.parametrize(("pattern", "key", "match"), [
    ("aermani/**", "aermani/v1/am1/camera/color", True),
    ("aermani/*/*/reasoner/**", "aermani/v1/am2/reasoner/step", True),
    ("aermani/*/am1/reasoner/step", "aermani/v1/am2/reasoner/step", False),
    ("aermani/v1/am1/**", "aermani/v1/am1", True),
    ("aermani/v1/*/camera/*", "aermani/v1/am1/camera/color/x", False),
    ("aermani/v1/am$*/tf", "aermani/v1/am7/tf", True),
])
def test_key_matches(pattern: str, key: str, match: bool) -> None:
    assert mcaplog.key_matches(pattern, key) is match


def test_publish_time_is_the_message_stamp() -> None:
    f = frames(123_456_789_000, 0)
    assert mcaplog.publish_time_ns("application/protobuf;foxglove.CompressedImage", f[K.camera_color], 1) \
        == 123_456_789_000
    assert mcaplog.publish_time_ns("application/protobuf;foxglove.CompressedImage", f[K.camera_depth], 1) \
        == 123_456_789_000
    assert mcaplog.publish_time_ns("application/protobuf;foxglove.RawImage", f[K.camera_segmentation], 1) \
        == 123_456_789_000
    data, enc = encode(VehicleState(stamp_ns=42))
    assert mcaplog.publish_time_ns(str(enc), data, 1) == 42
    assert mcaplog.publish_time_ns("zenoh/bytes", b"\x00", 7) == 7
    assert mcaplog.publish_time_ns("application/json;aermani.VehicleState", b"{broken", 9) == 9


def test_channel_specs() -> None:
    spec = mcaplog.channel_spec("application/protobuf;foxglove.RawImage")
    assert (spec.schema_name, spec.schema_encoding, spec.message_encoding) == ("foxglove.RawImage", "protobuf",
                                                                               "protobuf")
    spec = mcaplog.channel_spec("application/json;aermani.ReasoningStep")
    assert spec.schema_encoding == "jsonschema" and b"image_stamp_ns" in spec.schema_data
    assert not mcaplog.channel_spec("zenoh/bytes").has_schema


FOX_TOKEN = "fox-token-for-tests-5e1d"


def _fox_connect(url: str, origin: str | None = None, token: str | None = FOX_TOKEN, **headers: str):
    from websockets.sync.client import connect

    if origin is not None:
        headers["Origin"] = origin
    return connect(url + (f"/?token={token}" if token is not None else "/"), subprotocols=["foxglove.websocket.v1"],
                   additional_headers=headers, open_timeout=10)


def test_foxglove_live_server_checks_origin_and_token_then_streams(tmp_path: Path) -> None:
    """The live view over a real WebSocket: a web page's origin (evil.example, a sandboxed page's null, a
    look-alike, any localhost port) gets 403 and a client without the token 401, before anything is sent; a
    client with the token sees every channel advertised and gets the frames it subscribes to."""
    import json
    import struct

    from websockets.exceptions import InvalidStatus

    w = RecordWriter(settings(tmp_path, foxglove=True, foxglove_port=0, foxglove_token=FOX_TOKEN,
                              foxglove_allowed_origins=["https://app.foxglove.dev"]))
    w.start()
    try:
        stamp = time.time_ns()
        sent = frames(stamp)
        for key, data in sent.items():
            schema = "foxglove.CompressedImage" if key == K.camera_color else "foxglove.RawImage"
            assert w.submit(key, data, f"application/protobuf;{schema}", stamp)
        submit_model(w, K.autopilot_state, VehicleState())
        wait_for(lambda: w.written == 4)
        url = w.foxglove_url
        assert url.startswith("ws://127.0.0.1:") and not url.endswith(":0")
        for origin, token, status in (("http://evil.example", FOX_TOKEN, 403), ("null", FOX_TOKEN, 403),
                                      ("https://app.foxglove.dev.evil.example", FOX_TOKEN, 403),
                                      ("http://localhost:5173", FOX_TOKEN, 403), (None, None, 401),
                                      (None, "wrong-token", 401), ("https://app.foxglove.dev", None, 401)):
            with pytest.raises(InvalidStatus) as refused:
                _fox_connect(url, origin, token)
            assert refused.value.response.status_code == status, (origin, token)
        with _fox_connect(url, token=None, Authorization=f"Bearer {FOX_TOKEN}") as ws:  # a header works too
            assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"

        with _fox_connect(url, "https://app.foxglove.dev") as ws:
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo"
            adverts = json.loads(ws.recv(timeout=10))
            assert adverts["op"] == "advertise"
            channels = {c["topic"]: c for c in adverts["channels"]}
            assert channels[K.camera_color]["schemaName"] == "foxglove.CompressedImage"
            assert channels[K.camera_color]["encoding"] == "protobuf" and channels[K.camera_color]["schema"]
            assert channels[K.autopilot_state]["schemaName"] == "aermani.VehicleState"
            assert channels[K.autopilot_state]["schemaEncoding"] == "jsonschema"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7,
                                                                      "channelId": channels[K.camera_color]["id"]}]}))
            # The subscription takes effect when the server has read it: keep sending frames until one arrives.
            deadline = time.monotonic() + 30
            payloads = {}
            while True:
                assert time.monotonic() < deadline, "no frame reached the subscriber"
                t = time.time_ns()
                payloads[t] = frames(t)[K.camera_color]
                assert w.submit(K.camera_color, payloads[t], "application/protobuf;foxglove.CompressedImage", t)
                try:
                    msg = ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                if isinstance(msg, bytes):
                    break
            op, sid, log_time = struct.unpack_from("<BIQ", msg)
            assert (op, sid) == (1, 7) and msg[13:] == payloads[log_time]
    finally:
        w.stop()


def test_foxglove_settings_refuse_an_open_bind_without_a_token_and_inexact_origins(tmp_path: Path) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="AERMANI_RECORDER_FOXGLOVE_TOKEN"):
        settings(tmp_path, foxglove=True, foxglove_host="0.0.0.0")
    assert settings(tmp_path, foxglove=True, foxglove_host="0.0.0.0", foxglove_token=FOX_TOKEN).foxglove
    for bad in ("*", "https://app.foxglove.dev/", "http://localhost:*"):
        with pytest.raises(ValidationError, match="not an exact origin"):
            settings(tmp_path, foxglove_allowed_origins=[bad])


class SlowFile(io.RawIOBase):
    """A real file on a slow disk: every write takes 20 ms."""

    def __init__(self, path: Path) -> None:
        self.f = open(path, "wb")  # noqa: SIM115 - closed by close()

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        time.sleep(0.02)
        return self.f.write(b)

    def flush(self) -> None:
        self.f.flush()

    def fileno(self) -> int:
        return self.f.fileno()

    def tell(self) -> int:
        return self.f.tell()

    def close(self) -> None:
        super().close()  # flushes
        self.f.close()


def test_stop_drains_for_a_bounded_time_and_leaves_a_valid_file(tmp_path: Path) -> None:
    w = RecordWriter(settings(tmp_path, compression="none", queue_size=5000), opener=SlowFile)
    w.start()
    for i in range(3000):  # far more than the slow disk writes in the drain limit
        submit_model(w, K.reasoning_step, step_message("t", i + 1, "forward"))
    w.stop(drain_s=0.5, timeout=60)
    assert not w._thread.is_alive()
    assert w.dropped_at_stop > 0 and w.written + w.dropped_at_stop + w.lost_on_error == 3000
    [path] = sorted((tmp_path / "rec").glob("*.mcap"))
    assert count_messages(path) == w.written  # finished properly: footer, summary, every written message
