"""The recorder as a real process on a real Zenoh router: completeness, schemas, replay, SIGKILL recovery,
unwritable paths."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import jsonschema
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import make_reader

from shared import mcaplog
from shared.messages import MESSAGE_TYPES, Health, ReasoningStep, VehicleState
from shared.sensors import parse_depth
from tests.helpers import Stack, bus_for
from tests.recorder.samples import K, calibration, example, frames, step_message

pytestmark = pytest.mark.integration

FPS = 15.0
N_FRAMES = 30


def recorder_stack(tmp_path: Path, **env: str) -> Stack:
    base = {"AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec"), "AERMANI_RECORDER_HEALTH_PERIOD_S": "0.2"}
    return Stack(["recorder"], env={**base, **env}, log_dir=tmp_path / "logs", supervise=False)


async def wait_health(bus, pred, timeout: float = 60.0) -> Health:
    sub = bus.subscribe(K.health("recorder"), maxsize=50)
    try:
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            try:
                last = await sub.recv(timeout=max(0.1, deadline - time.monotonic()))
            except TimeoutError:
                break
            if pred(last):
                return last
        raise TimeoutError(f"recorder health never matched; last: {last}")
    finally:
        sub.close()


def single_file(tmp_path: Path) -> Path:
    files = sorted((tmp_path / "rec").glob("*.mcap"))
    assert len(files) == 1, files
    return files[0]


def aermani(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aermani.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "RUST_LOG": "error"})


async def publish_demo(bus) -> Counter:
    """Every message type once, and a task's worth of camera frames, transforms, states and steps at FPS."""
    sent: Counter = Counter()
    for i, cls in enumerate(MESSAGE_TYPES):
        key = K.key(f"test/{cls.__name__}")
        bus.publish(key, example(cls, i))
        sent[key] += 1
    bus.publish(K.camera_calibration, calibration(time.time_ns()))
    sent[K.camera_calibration] += 1
    t0 = time.monotonic()
    for n in range(N_FRAMES):
        stamp = time.time_ns()
        # Frames and state are declared best effort (late is worse than lost); here every sample must reach the
        # recorder so the counts can be compared, so they go reliably.
        for key, data in frames(stamp, n).items():
            bus.publish(key, data, reliable=True)
            sent[key] += 1
        bus.publish(K.autopilot_state, VehicleState(stamp_ns=stamp), reliable=True)
        sent[K.autopilot_state] += 1
        if n % 5 == 4:
            bus.publish(K.reasoning_step, step_message("task-1", n // 5 + 1, "forward", image_stamp_ns=stamp))
            sent[K.reasoning_step] += 1
        await asyncio.sleep(max(0.0, t0 + (n + 1) / FPS - time.monotonic()))
    return sent


async def test_records_every_key_with_schemas_then_replays_the_steps(tmp_path: Path) -> None:
    # Every frame (no rate limit: the counts are compared) and the oracle's masks too, as `sim` runs do.
    stack = recorder_stack(tmp_path, AERMANI_RECORDER_SEGMENTATION="1", AERMANI_RECORDER_FRAME_MAX_HZ="0")
    with stack:
        async def record() -> Counter:
            async with bus_for(stack) as bus:
                await wait_health(bus, lambda h: h.ok)
                sent = await publish_demo(bus)
                total = sum(sent.values())
                # Wait until the recorder has written everything we sent (its own health comes on top).
                await wait_health(bus, lambda h: h.details["written"] - h.details["received"] == 0
                                  and h.details["received"] >= total)
                return sent
        sent = await record()
    path = single_file(tmp_path)
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        got: Counter = Counter()
        publish_times: dict[str, list[int]] = {}
        for schema, channel, message in reader.iter_messages():
            got[channel.topic] += 1
            if channel.topic == K.camera_color:
                # A reader that knows only the Foxglove protobuf schemas.
                assert schema.name == "foxglove.CompressedImage" and schema.encoding == "protobuf"
                img = CompressedImage()
                img.ParseFromString(message.data)
                assert img.format == "jpeg" and img.data[:2] == b"\xff\xd8"
                stamp = img.timestamp.seconds * 10**9 + img.timestamp.nanos
                assert message.publish_time == stamp
                publish_times.setdefault(channel.topic, []).append(stamp)
            elif channel.topic == K.camera_depth:
                assert schema.name == "foxglove.CompressedImage"
                img = CompressedImage()
                img.ParseFromString(message.data)
                assert img.format == "png" and parse_depth(message.data)[1].shape == (120, 160)
            elif channel.topic == K.camera_segmentation:
                assert schema.name == "foxglove.RawImage"
                raw = RawImage()
                raw.ParseFromString(message.data)
                assert (raw.width, raw.height, raw.encoding) == (160, 120, "16UC1")
            elif channel.message_encoding == "json" and schema is not None:
                assert schema.encoding == "jsonschema"
                doc = json.loads(message.data)
                jsonschema.validate(doc, json.loads(schema.data))
                if "stamp_ns" in doc:
                    assert message.publish_time == doc["stamp_ns"]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    for key, n in sent.items():
        assert got[key] == n, f"{key}: recorded {got[key]} of {n}"
    assert got[K.health("recorder")] > 0
    assert summary.statistics.chunk_count >= 1
    assert meta["aermani"]["setting.key_expr"] == "aermani/**"
    assert "aermani_version" in meta["aermani"]
    assert meta["aermani.session"]["vehicles"] == "am1"
    steps_in_log = [s for _, s in mcaplog.read_messages(path, ReasoningStep)
                    if _.key == K.reasoning_step]
    assert [s.step for s in steps_in_log] == list(range(1, sent[K.reasoning_step] + 1))

    # Replay the step stream onto a fresh router: same bytes, same encoding, same order.
    replay_stack = Stack([], log_dir=tmp_path / "logs2", supervise=False)
    with replay_stack:
        async def replay() -> list:
            async with bus_for(replay_stack) as bus:
                sub = bus.subscribe(K.reasoning_step, maxsize=1000)
                await asyncio.sleep(0.5)  # let the subscription reach the router
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "aermani.cli", "replay", str(path), "--speed", "0",
                    "--keys", "aermani/*/*/reasoner/**", "--connect", replay_stack.endpoint)
                assert await asyncio.wait_for(proc.wait(), 120) == 0
                out = []
                while len(out) < sent[K.reasoning_step]:
                    out.append(await sub.recv_sample(timeout=30))
                return out
        replayed = await replay()
    originals = list(mcaplog.iter_samples(path, K.reasoning_step))
    assert [r.payload for r in replayed] == [s.payload for s in originals]
    assert all(r.encoding == "application/json;aermani.ReasoningStep" for r in replayed)

    # The readable timeline and the HTML report work on the same file.
    shown = aermani("log", "show", str(path), "--json")
    assert shown.returncode == 0, shown.stderr
    doc = json.loads(shown.stdout)
    assert doc["tasks"][0]["metrics"]["steps"] == sent[K.reasoning_step]
    exported = aermani("log", "export", str(path), "--out", str(tmp_path / "report"))
    assert exported.returncode == 0, exported.stderr
    html = (tmp_path / "report" / "index.html").read_text()
    assert html.count("<img") == sent[K.reasoning_step]


async def test_sigkill_then_recover_salvages_every_complete_chunk(tmp_path: Path) -> None:
    n_sent = 300
    stack = recorder_stack(tmp_path, AERMANI_RECORDER_CHUNK_SIZE="4096",
                           AERMANI_RECORDER_KEY_EXPR="aermani/*/*/autopilot/**")
    with stack:
        async def record_then_kill() -> Health:
            async with bus_for(stack) as bus:
                await wait_health(bus, lambda h: h.ok)
                for i in range(n_sent):  # reliably: the key is best effort, and this tests recovery, not the bus
                    bus.publish(K.autopilot_state, VehicleState(stamp_ns=1_000_000 + i, message=f"#{i}"),
                                reliable=True)
                # Nothing but our samples is recorded, so once all are written `durable` cannot change.
                h = await wait_health(bus, lambda h: h.details["written"] == n_sent)
                stack.kill("recorder", signal.SIGKILL)
                await asyncio.to_thread(stack.find("recorder").proc.wait, 30)
                return h
        health = await record_then_kill()
    broken = single_file(tmp_path)
    durable = health.details["durable"]
    # Some complete chunks; the chunk in progress (if the last message did not happen to close one) is lost.
    assert 0 < durable <= n_sent and health.details["file_messages"] == n_sent, health.details
    fixed = tmp_path / "fixed.mcap"
    res = aermani("log", "recover", str(broken), "--out", str(fixed))
    assert res.returncode == 0, res.stderr
    assert f"{durable} messages" in res.stdout
    with fixed.open("rb") as f:
        msgs = [VehicleState.model_validate_json(m.data) for _, _, m in make_reader(f).iter_messages()]
    assert len(msgs) == durable
    assert [s.message for s in msgs] == [f"#{i}" for i in range(durable)]  # a prefix, in order


async def test_unwritable_path_is_reported_on_health(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    stack = recorder_stack(tmp_path, AERMANI_RECORDER_OUT_DIR=str(blocker / "rec"))
    with stack:
        async def check() -> Health:
            async with bus_for(stack) as bus:
                bus.publish(K.autopilot_state, VehicleState())
                return await wait_health(bus, lambda h: not h.ok)
        health = await check()
        assert stack.find("recorder").running  # reported, not crashed
    assert "cannot open a recording" in health.message
    assert str(blocker) in health.message
