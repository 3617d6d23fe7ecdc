"""`aermani log export --format lerobot`: a log written by the real recorder writer (real bus messages, real
camera and depth encodings) becomes a LeRobot v3.0 dataset, read back with Hugging Face `datasets` and pyarrow
(what LeRobotDataset loads its files with; `lerobot` itself needs torch, which this machine cannot install) and
checked against LeRobot's own feature rules, reimplemented below. Plus the refusals (no steps, a non-empty
output), the --ros2 alias, and one export of a log the real reasoner and recorder processes wrote."""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from services.recorder.lerobot import (
    CAMERA,
    DEPTH,
    STATE,
    STATE_NAMES,
    LeRobotExportError,
    export_lerobot,
    skill_vocabulary,
)
from services.recorder.settings import RecorderSettings
from services.recorder.writer import RecordWriter
from shared import messages as m
from shared.bus import encode
from shared.keys import Keys
from shared.sensors import color_message, depth_message, encode_jpeg
from tests.recorder.samples import K, step_message
from tests.recorder.test_recording import aermani

# No test reaches the internet: `datasets` and the hub client read these when first imported.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

T0 = 1_700_000_000 * 10**9
MS = 10**6
A_CMD, B_CMD = "pick up the red cup and place it on the table", "pick up the tissue box"


def frame_rgb(n: int) -> np.ndarray:
    rng = np.random.default_rng(n)
    return rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)


def frame_depth(n: int) -> np.ndarray:
    d = np.full((48, 64), 1000 + n, dtype=np.uint16)
    d[:4, :4] = 0  # no return
    return d


def write_log(tmp_path: Path, *, steps: bool = True) -> Path:
    """Two tasks flown one after the other with camera (10 Hz), depth and state (20 Hz), each step decided on
    frame 3, 8, 13...; a third task refused before its first step; the real writer thread writes the file."""
    w = RecordWriter(RecorderSettings(out_dir=str(tmp_path / "rec"), chunk_size=1 << 16))
    w.start()

    def put(key: str, obj: object, at: int) -> None:
        data, enc = encode(obj)
        assert w.submit(key, data, str(enc), at + 2 * MS)

    plan = [("task-a", A_CMD, [("obj_localization", "red cup", None), ("grasp", None, m.OutcomeCode.MISSED),
                               (None, None, None), ("done", None, None)]),
            ("task-b", B_CMD, [("obj_localization", "tissue box", m.OutcomeCode.NOT_DETECTED),
                               ("yaw_left", None, None)])]
    frame = 0
    for task_id, cmd, chosen in plan:
        started = T0 + frame * 100 * MS
        put(K.task_status, m.TaskStatus(task_id=task_id, command=cmd, state=m.TaskState.RUNNING,
                                        started_ns=started, stamp_ns=started), started)
        for i, (skill, arg, code) in enumerate(chosen, 1):
            for _ in range(5):
                stamp = T0 + frame * 100 * MS
                put(K.camera_color, color_message(frame_rgb(frame), stamp), stamp)
                put(K.camera_depth, depth_message(frame_depth(frame), stamp), stamp)
                for half in (0, 50 * MS):
                    put(K.autopilot_state, m.VehicleState(
                        stamp_ns=stamp + half, position=m.Vec3(x=0.01 * frame, y=-1.0, z=1.2), yaw=0.1,
                        velocity=m.Vec3(x=0.2), gripper=m.GripperState.CLOSED if frame > 10 else m.GripperState.OPEN,
                        gripper_width=None if frame < 5 else 0.04, gripper_holding=frame > 10), stamp + half)
                frame += 1
            image_stamp = T0 + (frame - 2) * 100 * MS  # the step saw the frame before last
            if not steps:
                continue
            if skill is None:
                st = m.ReasoningStep(task_id=task_id, step=i, backend="rules", image_stamp_ns=image_stamp,
                                     prompt={"command": cmd}, calls=(m.ModelCall(raw_answer="oops", valid=False),),
                                     stamp_ns=image_stamp + 30 * MS)
            else:
                st = step_message(task_id, i, skill, arg, image_stamp_ns=image_stamp, command=cmd,
                                  state=m.SkillState.FAILED if code else m.SkillState.SUCCEEDED).model_copy(
                    update={"stamp_ns": image_stamp + 30 * MS,
                            "outcome": m.SkillOutcome(code=code) if code else None})
            put(K.reasoning_step, st, image_stamp + 30 * MS)
        ended = T0 + frame * 100 * MS
        put(K.task_status, m.TaskStatus(task_id=task_id, command=cmd, state=m.TaskState.SUCCEEDED, message="done",
                                        started_ns=started, ended_ns=ended, stamp_ns=ended), ended)
    refused = T0 + frame * 100 * MS
    put(K.task_status, m.TaskStatus(task_id="task-c", command="fly to the moon", state=m.TaskState.FAILED,
                                    message="refused", stamp_ns=refused), refused)
    w.stop()
    [log] = sorted((tmp_path / "rec").glob("*.mcap"))
    return log


# --------------------------------------------------------------------------- LeRobot's rules, reimplemented


DEFAULT_FEATURES = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
                    "task_index": "int64"}


def check_lerobot_features(features: dict) -> None:
    """What LeRobot requires of meta/info.json's features, reimplemented minimally from huggingface/lerobot
    src/lerobot/utils/constants.py (DEFAULT_FEATURES), src/lerobot/utils/feature_utils.py
    (`_validate_feature_names`: no '/' in a name; `hw_to_dataset_features` and `dataset_to_policy_features`:
    an image is (H, W, C) with names height/width/channels, C 3 or, flagged `info.is_depth_map`, 1) and
    src/lerobot/datasets/feature_utils.py (`validate_feature_dtype_and_shape`: a dtype is a numpy dtype,
    image, video, string or language; `get_hf_features_from_features`: the shapes it can map)."""
    for key, dtype in DEFAULT_FEATURES.items():
        assert features[key]["dtype"] == dtype and features[key]["shape"] == [1], key
    for key, ft in features.items():
        assert "/" not in key, key
        assert {"dtype", "shape", "names"} <= set(ft), key
        dtype, shape = ft["dtype"], tuple(ft["shape"])
        assert all(isinstance(n, int) and n > 0 for n in shape), key
        if dtype in ("image", "video"):
            assert len(shape) == 3 and ft["names"] == ["height", "width", "channels"], key
            assert shape[2] == (1 if ft.get("info", {}).get("is_depth_map") else 3), key
        elif dtype not in ("string", "language"):
            np.dtype(dtype)  # raises TypeError when not a numpy dtype, as is_valid_numpy_dtype_string checks
            assert 1 <= len(shape) <= 5, key
            if ft["names"] is not None and len(shape) == 1 and shape != (1,):
                assert len(ft["names"]) == shape[0], key
        else:
            assert shape == (1,), key
        # strings are not policy inputs: dataset_to_policy_features takes every observation*/action* key
        if dtype == "string":
            assert not key.startswith(("observation", "action")), key


def hf_features(features: dict):
    """`get_hf_features_from_features` (src/lerobot/datasets/feature_utils.py): how LeRobotDataset types the data
    files when it loads them."""
    import datasets

    out = {}
    for key, ft in features.items():
        if ft["dtype"] == "image":
            out[key] = datasets.Image()
        elif ft["shape"] == [1]:
            out[key] = datasets.Value(ft["dtype"])
        else:
            out[key] = datasets.Sequence(length=ft["shape"][0], feature=datasets.Value(ft["dtype"]))
    return datasets.Features(out)


def read_back(root: Path) -> tuple[dict, object, object]:
    """(info, the frames as LeRobotDataset loads them, meta/episodes)."""
    import datasets

    info = json.loads((root / "meta" / "info.json").read_text())
    files = sorted(str(p) for p in (root / "data").glob("*/*.parquet"))
    frames = datasets.load_dataset("parquet", data_files=files, split="train", features=hf_features(info["features"]),
                                   cache_dir=str(root.parent / "hf-cache"))
    episodes = datasets.load_dataset("parquet", data_files=str(root / "meta" / "episodes" / "chunk-000" /
                                                                "file-000.parquet"),
                                     split="train", cache_dir=str(root.parent / "hf-cache"))
    return info, frames, episodes


# --------------------------------------------------------------------------- the tests


def test_export_reads_back_with_datasets_and_keeps_every_step(tmp_path: Path) -> None:
    import pandas as pd

    log = write_log(tmp_path)
    out = tmp_path / "ds"
    t0 = time.monotonic()
    res = aermani("log", "export", str(log), "--out", str(out), "--format", "lerobot")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "wrote 2 episodes, 6 frames to" in res.stdout
    assert "left out 1 task(s) with no reasoning step: task-c" in res.stdout
    info, frames, episodes = read_back(out)
    print(f"export + read back: {time.monotonic() - t0:.1f} s")

    assert info["codebase_version"] == "v3.0" and info["fps"] == 1
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (2, 6, 2)
    assert info["splits"] == {"train": "0:2"} and info["video_path"] is None
    check_lerobot_features(info["features"])
    feats = info["features"]
    assert feats[CAMERA]["shape"] == [48, 64, 3] and feats[DEPTH]["shape"] == [48, 64, 1]
    assert feats[DEPTH]["info"] == {**feats[DEPTH]["info"], "is_depth_map": True, "depth_unit": "mm"}
    assert feats[STATE]["names"] == STATE_NAMES and set(frames.column_names) == set(feats)

    # Episodes: one per task with steps, their frame ranges tile the data in order.
    assert episodes["episode_index"] == [0, 1] and episodes["length"] == [4, 2]
    assert episodes["tasks"] == [[A_CMD], [B_CMD]]
    assert list(zip(episodes["dataset_from_index"], episodes["dataset_to_index"], strict=True)) == [(0, 4), (4, 6)]
    assert episodes["aermani/task_id"] == ["task-a", "task-b"] and episodes["aermani/state"] == ["succeeded"] * 2
    assert episodes["judge/success"] == [None, None] and episodes["judge/verdict"] == [None, None]
    for ep in episodes:
        path = out / info["data_path"].format(chunk_index=ep["data/chunk_index"], file_index=ep["data/file_index"])
        assert path.is_file()
        rows = frames.select(range(ep["dataset_from_index"], ep["dataset_to_index"]))
        assert rows["episode_index"] == [ep["episode_index"]] * ep["length"]
        assert rows["frame_index"] == list(range(ep["length"]))
        assert rows["timestamp"] == [float(i) for i in range(ep["length"])]  # frame_index / fps
    assert frames["index"] == list(range(6))
    # one row group per episode, as LeRobot writes its data files
    assert pq.ParquetFile(out / "data" / "chunk-000" / "file-000.parquet").num_row_groups == 2

    # Tasks, as LeRobot's load_tasks reads them (pandas, the task as the index).
    tasks = pd.read_parquet(out / "meta" / "tasks.parquet")
    assert tasks.index.name == "task" and list(tasks.index) == [A_CMD, B_CMD]
    assert [tasks.iloc[i].name for i in frames["task_index"]] == [A_CMD] * 4 + [B_CMD] * 2

    # The frames: the colour frame the step was decided on, byte for byte; depth exactly; the state then.
    decided = [3, 8, 13, 18, 23, 28]
    for row, n in zip(frames, decided, strict=True):
        img = row[CAMERA]
        assert img.size == (64, 48) and img.mode == "RGB"
        assert np.array(img).shape == tuple(feats[CAMERA]["shape"])
        depth = np.array(row[DEPTH])
        assert row[DEPTH].mode.startswith("I;16") and depth.shape == tuple(feats[DEPTH]["shape"][:2])
        assert (depth == frame_depth(n)).all()
        assert row["step.image_offset_s"] == 0.0
        st = dict(zip(STATE_NAMES, row[STATE], strict=True))
        assert st["x"] == pytest.approx(0.01 * n) and st["y"] == -1.0 and st["vx"] == pytest.approx(0.2)
        assert st["gripper_closed"] == (1.0 if n > 10 else 0.0) and st["gripper_holding"] == (1.0 if n > 10 else 0.0)
        assert np.isnan(st["gripper_width"]) if n < 5 else st["gripper_width"] == pytest.approx(0.04)
    raw = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet", columns=[CAMERA]).column(CAMERA).to_pylist()
    assert [r["bytes"] for r in raw] == [encode_jpeg(frame_rgb(n)) for n in decided]
    assert all(r["path"] is None for r in raw)

    # What was chosen, why, and how it went.
    vocab = feats["action"]["info"]["labels"]
    assert vocab[: len(skill_vocabulary([]))] == skill_vocabulary([])
    assert frames["skill"] == ["obj_localization", "grasp", "", "done", "obj_localization", "yaw_left"]
    assert frames["action"] == [vocab.index(s) if s else -1 for s in frames["skill"]]
    assert frames["skill_argument"] == ["red cup", "", "", "", "tissue box", ""]
    assert frames["drt.reasoning"][:2] == ["because step 1", "because step 2"] and frames["drt.reasoning"][2] == ""
    assert frames["step.valid"] == [True, True, False, True, True, True]
    assert frames["outcome.code"] == ["", "missed", "", "", "not_detected", ""]
    assert frames["outcome.ok"] == [True, False, False, True, False, True]
    assert frames["outcome.skill_state"][1] == "failed" and frames["outcome.skill_state"][2] == ""
    assert json.loads(frames["prompt"][0])["command"] == A_CMD
    assert frames["judge.success"] == [None] * 6 and frames["judge.verdict"] == [None] * 6
    assert "no judge verdict" in feats["judge.success"]["info"]["description"]

    # Stats as LeRobot keeps them: vectors per dimension, images per channel (C, 1, 1), colour in [0, 1].
    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert {"min", "max", "mean", "std", "count", "q01", "q50", "q99"} <= set(stats[STATE])
    assert len(stats[STATE]["mean"]) == len(STATE_NAMES) and stats[STATE]["count"] == [6]
    assert stats[STATE]["min"][STATE_NAMES.index("x")] == pytest.approx(0.03)
    assert np.array(stats[CAMERA]["mean"]).shape == (3, 1, 1) and np.min(stats[CAMERA]["min"]) >= 0
    assert np.max(stats[CAMERA]["max"]) <= 1.0
    assert np.array(stats[DEPTH]["max"]).shape == (1, 1, 1) and stats[DEPTH]["max"] == [[[1028.0]]]
    assert stats["action"]["min"] == [-1.0]

    # A plain load_dataset without LeRobot's features decodes the images too (the files' schema metadata).
    import datasets

    plain = datasets.load_dataset("parquet", data_files=str(out / "data" / "chunk-000" / "file-000.parquet"),
                                  split="train", cache_dir=str(tmp_path / "hf-cache2"))
    assert isinstance(plain.features[CAMERA], datasets.Image) and isinstance(plain.features[DEPTH], datasets.Image)
    assert plain.features[STATE].length == len(STATE_NAMES)


def test_a_log_without_steps_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    log = write_log(tmp_path, steps=False)
    out = tmp_path / "ds"
    res = aermani("log", "export", str(log), "--out", str(out), "--format", "lerobot")
    assert res.returncode == 2 and "has no reasoning step" in res.stderr, res.stdout + res.stderr
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".ds")] == []  # no temporary left behind


def test_a_non_empty_output_is_refused_unless_an_earlier_export_is_overwritten(tmp_path: Path) -> None:
    log = write_log(tmp_path)
    out = tmp_path / "ds"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(LeRobotExportError, match="not empty: pass --overwrite"):
        export_lerobot(log, out)
    with pytest.raises(LeRobotExportError, match="not a LeRobot dataset"):
        export_lerobot(log, out, overwrite=True)  # never deletes what an export did not write
    assert (out / "notes.txt").read_text() == "mine"
    fresh = tmp_path / "ds2"
    assert export_lerobot(log, fresh).frames == 6
    res = aermani("log", "export", str(log), "--out", str(fresh), "--format", "lerobot")
    assert res.returncode == 2 and "--overwrite" in res.stderr
    res = aermani("log", "export", str(log), "--out", str(fresh), "--format", "lerobot", "--overwrite")
    assert res.returncode == 0, res.stderr
    assert json.loads((fresh / "meta" / "info.json").read_text())["total_frames"] == 6
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".ds")) == []


def test_ros2_flag_is_still_the_ros2_format(tmp_path: Path) -> None:
    log = write_log(tmp_path)
    for args, bag in ((["--ros2"], "bag1"), (["--format", "ros2"], "bag2")):
        res = aermani("log", "export", str(log), "--out", str(tmp_path / bag), *args)
        assert res.returncode == 0, res.stderr
        assert (tmp_path / bag / "metadata.yaml").is_file()
    res = aermani("log", "export", str(log), "--out", str(tmp_path / "bag3"), "--ros2", "--format", "lerobot")
    assert res.returncode == 2 and "contradict" in res.stderr


def test_vehicle_filter_and_missing_depth(tmp_path: Path) -> None:
    """Another vehicle's steps are left out with --vehicle; a log without depth has no depth feature."""
    w = RecordWriter(RecorderSettings(out_dir=str(tmp_path / "rec")))
    w.start()
    for vid, n in (("am1", 2), ("am2", 3)):
        keys = Keys(vid)
        for i in range(1, n + 1):
            stamp = T0 + (10 * i) * MS
            data, enc = encode(step_message(f"{vid}-task", i, "forward", image_stamp_ns=stamp))
            w.submit(keys.reasoning_step, data, str(enc), stamp)
            w.submit(keys.camera_color, color_message(frame_rgb(i), stamp), "application/protobuf;"
                     "foxglove.CompressedImage", stamp)
    w.stop()
    [log] = sorted((tmp_path / "rec").glob("*.mcap"))
    res = export_lerobot(log, tmp_path / "am2", "am2")
    assert (res.episodes, res.frames) == (1, 3)
    info = json.loads((tmp_path / "am2" / "meta" / "info.json").read_text())
    assert CAMERA in info["features"] and DEPTH not in info["features"]
    check_lerobot_features(info["features"])
    both = export_lerobot(log, tmp_path / "both")
    assert (both.episodes, both.frames) == (2, 5)
    _, frames, _ = read_back(tmp_path / "both")
    assert all(np.isnan(v) for v in frames[STATE][0])  # no state recorded: NaN, not zeros


# --------------------------------------------------------------------------- the real processes


@pytest.mark.integration
async def test_export_of_a_log_the_real_reasoner_and_recorder_wrote(tmp_path: Path) -> None:
    """The rules policy in the real reasoner process runs two tasks against a scripted world while a camera
    publishes colour and depth; the real recorder process writes the log; it exports to two episodes whose
    frames are the recorded steps, with the frame each was decided on."""
    from tests.helpers import bus_for, run_stack
    from tests.reasoner.fake_world import MiniWorld, Thing, serve_executor

    async def camera(bus) -> None:
        n = 0
        while True:
            stamp = time.time_ns()
            bus.publish(K.camera_color, color_message(frame_rgb(n % 7), stamp))
            bus.publish(K.camera_depth, depth_message(frame_depth(n % 7), stamp))
            n += 1
            await asyncio.sleep(0.1)

    env = {"AERMANI_REASONER_BACKEND": "rules", "AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec"),
           "AERMANI_RECORDER_HEALTH_PERIOD_S": "0.5"}
    commands = ["Pick up the red cup and place it on the table", "Pick up the red cup and place it on the table"]
    t0 = time.monotonic()
    with run_stack(["reasoner", "recorder"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            await bus.subscribe(K.health("recorder"), maxsize=10).recv(timeout=60)
            cam = asyncio.create_task(camera(bus))
            statuses = bus.subscribe(K.task_status, maxsize=100)
            try:
                for cmd in commands:
                    world = MiniWorld([Thing("red cup"), Thing("table", "surface", headings=tuple(range(8)))])
                    ticker = await serve_executor(bus, world, K, skill_delay=0.1)
                    try:
                        await asyncio.sleep(0.5)
                        accept = await bus.query(K.start_task, m.TaskRequest(command=cmd), timeout=10)
                        assert accept.accepted, accept.reason
                        while not (st := await statuses.recv(timeout=120)).state.terminal:
                            pass
                        assert st.state is m.TaskState.SUCCEEDED, st.message
                    finally:
                        ticker.cancel()
                await asyncio.sleep(1.0)  # the last samples reach the recorder
            finally:
                cam.cancel()
    [log] = sorted((tmp_path / "rec").glob("*.mcap"))
    from shared.mcaplog import reasoning_steps

    steps = reasoning_steps(log)
    res = aermani("log", "export", str(log), "--out", str(tmp_path / "ds"), "--format", "lerobot")
    assert res.returncode == 0, res.stdout + res.stderr
    info, frames, episodes = read_back(tmp_path / "ds")
    print(f"real stack, two tasks, export and read back: {time.monotonic() - t0:.1f} s")
    check_lerobot_features(info["features"])
    assert info["total_episodes"] == 2 and info["total_frames"] == len(steps)
    assert frames["skill"] == [s.ste.skill if s.ste else "" for s in steps]
    assert frames["skill"][-1] == "done" and "grasp" in frames["skill"]
    assert len(set(episodes["aermani/task_id"])) == 2
    assert all(a == pytest.approx(0.0, abs=1e-6) for a in frames["step.image_offset_s"])  # the frame it saw
    for row, st in zip(frames, steps, strict=True):
        assert (np.array(row[DEPTH]) > 0).any() and np.array(row[CAMERA]).shape == (48, 64, 3)
        assert row["step.stamp_ns"] == st.stamp_ns
        assert row[STATE][2] == pytest.approx(1.2)  # the scripted world flies at 1.2 m once airborne
