"""Export a recorder log as a training dataset in the LeRobot dataset format v3.0 (`aermani log export --format
lerobot`): one frame per reasoning step, one episode per task.

The VLM acts once per step, so a frame is a step: the colour frame and the depth image the decision was made on
(the ones closest to the step's `image_stamp_ns`, as the HTML report picks them), the vehicle state closest to
the same stamp, the chosen skill and its argument (as text, and as an index into the skill vocabulary), the
step's DRT, the skill's outcome, and the episode's judge verdict. The layout is LeRobot's v3.0 one (learned from
huggingface/lerobot `src/lerobot/datasets/utils.py`, `io_utils.py`, `dataset_writer.py`,
`dataset_metadata.py`, `feature_utils.py`; no code copied):

    DIR/meta/info.json                          codebase_version v3.0, fps, features (dtype, shape, names)
    DIR/meta/stats.json                         min, max, mean, std, count (and quantiles of vectors)
    DIR/meta/tasks.parquet                      the commands; index "task", column task_index
    DIR/meta/episodes/chunk-000/file-000.parquet  one row per episode: length, data file, frame range, task...
    DIR/data/chunk-000/file-000.parquet         the frames, one row group per episode (new file past 100 MB)

Images are embedded in the parquet as {bytes, path: None} (dtype "image"; no video, which needs ffmpeg): the
colour frame keeps the recorded JPEG bytes (no re-encoding loss), depth is a 16-bit greyscale PNG of millimetres
(the bus's own bytes). The dataset's fps is 1 by convention: steps come at irregular times, so `timestamp` is
`frame_index / fps` (what LeRobot's timestamp checks expect) and the real time is in `step.stamp_ns`.

The judge's verdict: a recorder log holds none (the simulator's judge answers a query, and the recorder records
published samples, not query replies; `aermani eval` starts no recorder; `aermani demo` prints its verdict).
The judge columns are written null then, never guessed from the reasoner's own end state (that is
`episode.state`).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.recorder.timeline import TaskTimeline, timelines
from shared.errors import AermaniError
from shared.keys import AUTOPILOT_STATE, CAMERA_COLOR, CAMERA_DEPTH
from shared.mcaplog import iter_samples, reasoning_steps
from shared.messages import GripperState, ReasoningStep, SkillState, VehicleState
from shared.sensors import DEPTH_FORMAT, CompressedImage, decode_depth, decode_jpeg, decode_proto, stamp_to_ns

CODEBASE_VERSION = "v3.0"
FPS = 1
CHUNKS_SIZE = 1000  # files per chunk directory (LeRobot's default)
DATA_FILES_SIZE_IN_MB = 100  # a data file is closed past this size (LeRobot's default)
ROBOT_TYPE = "aermani_px4_gripper"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)  # LeRobot's DEFAULT_QUANTILES

CAMERA = "observation.images.camera"
DEPTH = "observation.images.camera_depth"
STATE = "observation.state"
STATE_NAMES = ["x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw", "gripper_closed", "gripper_width",
               "gripper_holding"]
NO_SKILL = -1
NO_VERDICT = ("null: a recorder log carries no judge verdict (the simulator's judge answers a query, which the "
              "recorder does not record)")


class LeRobotExportError(AermaniError):
    """The log cannot be exported (no reasoning step, the output exists, frames of different sizes)."""


Progress = Callable[[int, int], None]
"""on_progress(samples read, samples in the log): called while the log is read."""


@dataclass
class LeRobotExport:
    """What an export wrote."""

    path: Path
    episodes: int = 0
    frames: int = 0
    features: list[str] = field(default_factory=list)
    tasks_without_steps: list[str] = field(default_factory=list)
    missing: Counter[str] = field(default_factory=Counter)
    """Modality -> frames written without it (no such sample recorded for that vehicle)."""

    def render(self) -> str:
        lines = [f"wrote {self.episodes} episodes, {self.frames} frames to {self.path}"]
        if self.missing:
            lines.append("frames without: " + ", ".join(f"{k} ({n})" for k, n in sorted(self.missing.items())))
        if self.tasks_without_steps:
            lines.append(f"left out {len(self.tasks_without_steps)} task(s) with no reasoning step: "
                         + ", ".join(self.tasks_without_steps))
        return "\n".join(lines)


# --------------------------------------------------------------------------- reading the log


@dataclass
class _Target:
    """One frame to be: a step, the stamp its observations are matched to, and what was matched."""

    episode: int
    tl: TaskTimeline
    step: ReasoningStep
    stamp_ns: int
    picked: dict[str, tuple[int, bytes]] = field(default_factory=dict)
    """kind (color, depth, state) -> (sample stamp, payload) of the closest sample so far."""
    images: dict[str, bytes] = field(default_factory=dict)
    """feature (CAMERA, DEPTH) -> the image bytes to write of the picked frame (once decoded and checked)."""


def _sample_stamp(kind: str, payload: bytes, fallback_ns: int) -> int:
    try:
        if kind == "state":
            return VehicleState.model_validate_json(payload).stamp_ns or fallback_ns
        return stamp_to_ns(decode_proto(CompressedImage, payload).timestamp) or fallback_ns
    except Exception:  # an undecodable sample is matched by its recorded time; decoding it later says more
        return fallback_ns


def _pick_closest(log: str | Path, targets: list[_Target], on_progress: Progress | None) -> None:
    """One pass over the log: for every target, the colour frame, depth image and vehicle state whose stamp is
    closest to the target's. Only the best candidate of each is held, so memory is about the output's."""
    by_key: dict[str, tuple[str, np.ndarray, list[int]]] = {}
    for vid in {t.tl.vehicle_id for t in targets}:
        idx = [i for i, t in enumerate(targets) if t.tl.vehicle_id == vid]
        stamps = np.array([targets[i].stamp_ns for i in idx], dtype=np.int64)
        for kind, key in (("color", CAMERA_COLOR.bind(vid).key), ("depth", CAMERA_DEPTH.bind(vid).key),
                          ("state", AUTOPILOT_STATE.bind(vid).key)):
            by_key[key] = (kind, stamps, idx)
    best = {key: np.full(len(v[2]), np.iinfo(np.int64).max, dtype=np.int64) for key, v in by_key.items()}
    total = _message_count(log)
    for n, s in enumerate(iter_samples(log), 1):
        if on_progress is not None and n % 200 == 0:
            on_progress(n, total)
        hit = by_key.get(s.key)
        if hit is None:
            continue
        kind, stamps, idx = hit
        t = _sample_stamp(kind, s.payload, s.publish_time_ns)
        dt = np.abs(stamps - t)
        better = dt < best[s.key]
        if better.any():
            best[s.key][better] = dt[better]
            for j in np.flatnonzero(better):
                targets[idx[j]].picked[kind] = (t, s.payload)
    if on_progress is not None:
        on_progress(total, total)


def _message_count(log: str | Path) -> int:
    from mcap.reader import make_reader

    try:
        with Path(log).open("rb") as f:
            summary = make_reader(f).get_summary()
        if summary is not None and summary.statistics is not None:
            return int(summary.statistics.message_count)
    except Exception:  # an unfinished log: iter_samples salvages it; the count is only for the progress bar
        pass
    return 0


# --------------------------------------------------------------------------- one frame's values


def skill_vocabulary(steps: list[ReasoningStep]) -> list[str]:
    """The built-in Skill Library's names in its order, then any other skill the log's steps chose (a skill
    module of AERMANI_EXECUTOR_SKILL_MODULES), in order of first use."""
    from shared.skills import builtin_library

    names = [s.name for s in builtin_library().skills]
    for st in steps:
        if st.ste is not None and st.ste.skill not in names:
            names.append(st.ste.skill)
    return names


def state_vector(payload: bytes | None) -> list[float]:
    """observation.state from a VehicleState (NaN where the vehicle did not report a value, or no state)."""
    nan = float("nan")
    if payload is None:
        return [nan] * len(STATE_NAMES)
    try:
        s = VehicleState.model_validate_json(payload)
    except ValueError:
        return [nan] * len(STATE_NAMES)
    closed = {GripperState.CLOSED: 1.0, GripperState.OPEN: 0.0}.get(s.gripper, nan)
    holding = nan if s.gripper_holding is None else float(s.gripper_holding)
    width = nan if s.gripper_width is None else float(s.gripper_width)
    return [s.position.x, s.position.y, s.position.z, s.velocity.x, s.velocity.y, s.velocity.z, s.roll, s.pitch,
            s.yaw, closed, width, holding]


def _color(payload: bytes) -> tuple[bytes, np.ndarray]:
    """(image bytes as recorded, HxWx3 uint8)."""
    msg = decode_proto(CompressedImage, payload)
    return bytes(msg.data), decode_jpeg(bytes(msg.data))


def _depth(payload: bytes) -> tuple[bytes, np.ndarray]:
    """(16-bit PNG bytes, HxW uint16 mm): the bus's PNG as it is; an older log's RawImage is encoded."""
    from shared.sensors import encode_depth_png

    _, _, img = decode_depth(payload)
    msg = decode_proto(CompressedImage, payload)
    data = bytes(msg.data) if msg.format == DEPTH_FORMAT else encode_depth_png(img)
    return data, img


def _text(value: str | None) -> str:
    return value or ""


# --------------------------------------------------------------------------- features


def features(shapes: dict[str, tuple[int, ...]], skills: list[str]) -> dict[str, dict[str, Any]]:
    """meta/info.json's features: LeRobot's five index columns, then aermani's."""

    def one(dtype: str, description: str, names: list[str] | None = None) -> dict[str, Any]:
        return {"dtype": dtype, "shape": [1], "names": names, "info": {"description": description}}

    out: dict[str, dict[str, Any]] = {
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    if CAMERA in shapes:
        out[CAMERA] = {"dtype": "image", "shape": list(shapes[CAMERA]), "names": ["height", "width", "channels"],
                       "info": {"is_depth_map": False, "description": "the colour frame the step was decided on "
                                "(closest to its image stamp), the recorded JPEG"}}
    if DEPTH in shapes:
        out[DEPTH] = {"dtype": "image", "shape": list(shapes[DEPTH]), "names": ["height", "width", "channels"],
                      "info": {"is_depth_map": True, "depth_unit": "mm",
                               "description": "depth aligned to the colour frame: 16-bit greyscale PNG, "
                               "millimetres, 0 = no return"}}
    out[STATE] = {"dtype": "float32", "shape": [len(STATE_NAMES)], "names": list(STATE_NAMES),
                  "info": {"description": "the vehicle state closest to the step's image stamp: position (m) and "
                           "velocity (m/s) in the world frame (ENU), roll/pitch/yaw (rad), gripper_closed (1 "
                           "closed, 0 open), gripper_width (m), gripper_holding (1/0); NaN where not reported"}}
    out["action"] = {"dtype": "int64", "shape": [1], "names": ["skill_index"],
                     "info": {"labels": skills, "description": "the chosen skill as an index into labels (the "
                              "built-in Skill Library, then other skills the log used); -1: no valid answer"}}
    out.update({
        "skill": one("string", "the chosen skill's name ('' when the step had no valid answer)"),
        "skill_argument": one("string", "the chosen skill's argument ('' when it has none)"),
        "drt.image_description": one("string", "DRT: what the model saw"),
        "drt.summary": one("string", "DRT: its summary of the task so far"),
        "drt.action_predictions": one("string", "DRT: its predicted effect of each candidate skill (JSON)"),
        "drt.reasoning": one("string", "DRT: why it chose the skill"),
        "prompt": one("string", "the prompt's parts the model was shown (JSON object: command, history...)"),
        "outcome.skill_state": one("string", "how the skill ended: succeeded, failed, aborted...; '' not run"),
        "outcome.ok": one("bool", "the skill succeeded"),
        "outcome.code": one("string", "the executor's outcome code (succeeded, not_detected, missed...; '' none)"),
        "outcome.message": one("string", "the executor's message"),
        "outcome.duration_s": one("float32", "how long the skill ran, s"),
        "step.number": one("int64", "the reasoner's step number in its task"),
        "step.valid": one("bool", "the model gave a valid answer"),
        "step.retries": one("int64", "re-prompts after invalid answers"),
        "step.stamp_ns": one("int64", "when the step was decided (ns since epoch)"),
        "step.image_offset_s": one("float32", "colour frame stamp minus the step's image stamp, s (NaN: no frame)"),
        "judge.success": one("bool", "the simulator judge's verdict on the episode; " + NO_VERDICT),
        "judge.verdict": one("string", "the judge's explanation; " + NO_VERDICT),
    })
    return out


def _hf_features(feats: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The `datasets` features of the data files, for their schema metadata (what `load_dataset("parquet")`
    decodes images by). "Sequence" is read by datasets 3 and later alike."""
    out: dict[str, Any] = {}
    for key, ft in feats.items():
        if ft["dtype"] == "image":
            out[key] = {"_type": "Image"}
        elif ft["shape"] == [1]:
            out[key] = {"dtype": ft["dtype"], "_type": "Value"}
        else:
            out[key] = {"feature": {"dtype": ft["dtype"], "_type": "Value"}, "length": ft["shape"][0],
                        "_type": "Sequence"}
    return out


# --------------------------------------------------------------------------- writing


def _arrow_type(ft: dict[str, Any]) -> Any:
    import pyarrow as pa

    scalar = {"float32": pa.float32(), "int64": pa.int64(), "bool": pa.bool_(), "string": pa.string()}
    if ft["dtype"] == "image":
        return pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    if ft["shape"] == [1]:
        return scalar[ft["dtype"]]
    return pa.list_(scalar[ft["dtype"]], ft["shape"][0])


class _Stats:
    """Running per-channel stats of an image feature (LeRobot keeps them channel-first, shape (C, 1, 1); colour
    scaled to [0, 1], depth in its unit)."""

    def __init__(self, scale: float) -> None:
        self.scale = scale
        self.n = 0
        self.sum: np.ndarray | None = None
        self.sq: np.ndarray | None = None
        self.min: np.ndarray | None = None
        self.max: np.ndarray | None = None

    def add(self, img: np.ndarray) -> None:
        px = img.reshape(-1, img.shape[2] if img.ndim == 3 else 1).astype(np.float64) / self.scale
        s, q, lo, hi = px.sum(0), (px * px).sum(0), px.min(0), px.max(0)
        if self.sum is None or self.sq is None or self.min is None or self.max is None:
            self.sum, self.sq, self.min, self.max = s, q, lo, hi
        else:
            self.sum, self.sq = self.sum + s, self.sq + q
            self.min, self.max = np.minimum(self.min, lo), np.maximum(self.max, hi)
        self.n += px.shape[0]

    def result(self, frames: int) -> dict[str, Any]:
        assert self.sum is not None and self.sq is not None and self.min is not None and self.max is not None
        mean = self.sum / self.n
        std = np.sqrt(np.maximum(self.sq / self.n - mean * mean, 0.0))

        def chw(v: np.ndarray) -> list[Any]:
            return [[[float(x)]] for x in v]

        return {"min": chw(self.min), "max": chw(self.max), "mean": chw(mean), "std": chw(std), "count": [frames]}


def _vector_stats(values: np.ndarray) -> dict[str, Any]:
    """Per-dimension stats of a numeric column; NaN (a value not reported) is left out, and a dimension never
    reported has null stats."""
    import warnings

    v = values.astype(np.float64).reshape(len(values), -1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice": that dimension's stats are null
        parts = {"min": np.nanmin(v, 0), "max": np.nanmax(v, 0), "mean": np.nanmean(v, 0), "std": np.nanstd(v, 0)}
        parts.update({f"q{int(q * 100):02d}": np.nanquantile(v, q, axis=0) for q in QUANTILES})
    out: dict[str, Any] = {k: [None if np.isnan(x) else float(x) for x in arr] for k, arr in parts.items()}
    out["count"] = [len(values)]
    return out


def _tasks_table(tasks: list[str]) -> Any:
    """meta/tasks.parquet as LeRobot reads it (pandas, the task text as the index): the pandas metadata is
    written by hand, so exporting needs no pandas."""
    import pyarrow as pa

    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())})
    meta = {"index_columns": ["task"], "column_indexes": [], "columns": [
        {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
         "metadata": None},
        {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None}],
        "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.0.0"}
    return table.replace_schema_metadata({"pandas": json.dumps(meta)})


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise LeRobotExportError(f"{out} is a file: a LeRobot export writes a directory")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise LeRobotExportError(f"{out} is not empty: pass --overwrite to replace it")
        if not (out / "meta" / "info.json").is_file():
            raise LeRobotExportError(f"{out} is not empty and is not a LeRobot dataset (no meta/info.json): "
                                     "--overwrite only replaces an earlier export")


def export_lerobot(log: str | Path, out: str | Path, vehicle: str | None = None, *, overwrite: bool = False,
                   on_progress: Progress | None = None) -> LeRobotExport:
    """Write the log's tasks as a LeRobot v3.0 dataset directory `out` (see the module's docstring). The
    dataset is written beside `out` and moved into place at the end: a failed export leaves nothing behind."""
    out = Path(out)
    _check_out(out, overwrite)
    raw = {(s.task_id, s.step): s for s in reasoning_steps(log, vehicle)}
    tls = timelines(log, vehicle)
    result = LeRobotExport(out)
    episodes = [tl for tl in tls if tl.steps]
    result.tasks_without_steps = [tl.task_id for tl in tls if not tl.steps]
    if not episodes:
        raise LeRobotExportError(f"{log} has no reasoning step" + (f" of vehicle {vehicle}" if vehicle else "")
                                 + ": nothing to export")
    targets = [_Target(e, tl, st, st.image_stamp_ns or st.stamp_ns)
               for e, tl in enumerate(episodes) for r in tl.steps if (st := raw.get((tl.task_id, r.step)))]
    _pick_closest(log, targets, on_progress)
    image_stats = {CAMERA: _Stats(255.0), DEPTH: _Stats(1.0)}
    shapes = _decode_picked(targets, result.missing, image_stats)
    skills = skill_vocabulary([t.step for t in targets])
    feats = features(shapes, skills)
    tasks = list(dict.fromkeys(tl.command for tl in episodes))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))  # same file system: moved, not copied
    try:
        ep_rows, columns = _write_data(tmp, episodes, targets, feats, tasks, skills)
        _write_meta(tmp, feats, ep_rows, tasks, columns, image_stats, len(targets))
        if out.exists():
            shutil.rmtree(out)  # _check_out allowed it: empty, or an earlier export with --overwrite
        tmp.replace(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result.episodes, result.frames, result.features = len(episodes), len(targets), list(feats)
    return result


def _decode_picked(targets: list[_Target], missing: Counter[str],
                   stats: dict[str, _Stats]) -> dict[str, tuple[int, ...]]:
    """Decode each target's colour frame and depth image: its `images` get the bytes to write, `stats` the
    pixels (which are not kept). Returns the features' shapes, from the frames (one camera per log); a modality
    the log has for no step at all is left out of the features."""
    shapes: dict[str, tuple[int, ...]] = {}
    for t in targets:
        for kind, key, decode in (("color", CAMERA, _color), ("depth", DEPTH, _depth)):
            got = None
            if kind in t.picked:
                stamp, payload = t.picked[kind]
                t.picked[kind] = (stamp, b"")  # the payload is done with: memory holds the bytes to write only
                try:
                    got = decode(payload)
                except Exception:  # an undecodable frame counts as none
                    got = None
            if got is None:
                missing[key] += 1
                continue
            data, pixels = got
            shape = pixels.shape if pixels.ndim == 3 else (*pixels.shape, 1)
            if shapes.setdefault(key, shape) != shape:
                raise LeRobotExportError(f"{key}: frames of {shapes[key]} and {shape} in one log (task "
                                         f"{t.tl.task_id}, step {t.step.step}); a dataset has one shape")
            t.images[key] = data
            stats[key].add(pixels)
    for key in (CAMERA, DEPTH):
        if key not in shapes:
            missing.pop(key, None)
    return shapes


def frame_values(t: _Target, frame_index: int, index: int, task_index: int, skills: list[str]) -> dict[str, Any]:
    """One frame's columns (the images aside)."""
    st, state, drt, ste = t.step, t.picked.get("state"), t.step.drt, t.step.ste
    color = t.picked.get("color") if CAMERA in t.images else None
    return {
        "timestamp": frame_index / FPS, "frame_index": frame_index, "episode_index": t.episode, "index": index,
        "task_index": task_index, STATE: state_vector(state[1] if state else None),
        "action": skills.index(ste.skill) if ste else NO_SKILL,
        "skill": ste.skill if ste else "", "skill_argument": _text(ste.argument if ste else None),
        "drt.image_description": _text(drt.image_description if drt else None),
        "drt.summary": _text(drt.summary if drt else None),
        "drt.action_predictions": json.dumps(drt.action_predictions) if drt and drt.action_predictions else "",
        "drt.reasoning": _text(drt.reasoning if drt else None),
        "prompt": json.dumps(st.prompt, ensure_ascii=False),
        "outcome.skill_state": str(st.skill_state) if st.skill_state else "",
        "outcome.ok": st.skill_state is SkillState.SUCCEEDED,
        "outcome.code": str(st.outcome.code) if st.outcome and st.outcome.code else "",
        "outcome.message": st.skill_message, "outcome.duration_s": st.skill_duration_s,
        "step.number": st.step, "step.valid": st.valid, "step.retries": st.retries, "step.stamp_ns": st.stamp_ns,
        "step.image_offset_s": (color[0] - t.stamp_ns) / 1e9 if color else float("nan"),
        "judge.success": None, "judge.verdict": None,
    }


def _write_data(root: Path, episodes: list[TaskTimeline], targets: list[_Target], feats: dict[str, dict[str, Any]],
                tasks: list[str], skills: list[str]) -> tuple[list[dict[str, Any]], dict[str, list[Any]]]:
    """data/chunk-*/file-*.parquet, one row group per episode, a new file past DATA_FILES_SIZE_IN_MB (an episode
    never straddles two). Returns the episodes' rows and the numeric columns, for meta/."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = pa.schema([(k, _arrow_type(ft)) for k, ft in feats.items()],
                       metadata={"huggingface": json.dumps({"info": {"features": _hf_features(feats)}})})
    columns: dict[str, list[Any]] = {k: [] for k, ft in feats.items() if ft["dtype"] not in ("image", "string", "bool")}
    ep_rows: list[dict[str, Any]] = []
    writer: Any = None
    chunk = file = index = 0
    for e, tl in enumerate(episodes):
        rows = [t for t in targets if t.episode == e]
        data: dict[str, list[Any]] = {k: [] for k in feats}
        for frame_index, t in enumerate(rows):
            values = frame_values(t, frame_index, index + frame_index, tasks.index(tl.command), skills)
            for key in (CAMERA, DEPTH):
                if key in feats:
                    data_bytes = t.images.get(key)
                    values[key] = {"bytes": data_bytes, "path": None} if data_bytes is not None else None
            for k in feats:
                data[k].append(values[k])
            for k in columns:
                columns[k].append(values[k])
        path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
        if writer is not None and path.stat().st_size / 2**20 >= DATA_FILES_SIZE_IN_MB:
            writer.close()
            writer = None
            chunk, file = (chunk + 1, 0) if file + 1 >= CHUNKS_SIZE else (chunk, file + 1)
            path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
        if writer is None:
            path.parent.mkdir(parents=True, exist_ok=True)
            writer = pq.ParquetWriter(path, schema, compression="snappy")
        writer.write_table(pa.Table.from_pydict(data, schema=schema))  # one row group per episode, as LeRobot's
        ep_rows.append({
            "episode_index": e, "tasks": [tl.command], "length": len(rows),
            "data/chunk_index": chunk, "data/file_index": file,
            "dataset_from_index": index, "dataset_to_index": index + len(rows),
            "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
            "aermani/task_id": tl.task_id, "aermani/vehicle_id": tl.vehicle_id, "aermani/backend": tl.backend,
            "aermani/variant": tl.variant, "aermani/state": tl.state, "aermani/message": tl.message,
            "aermani/started_ns": tl.started_ns, "aermani/ended_ns": tl.ended_ns,
            "judge/success": None, "judge/verdict": None,
        })
        index += len(rows)
    if writer is not None:
        writer.close()
    return ep_rows, columns


def _write_meta(root: Path, feats: dict[str, dict[str, Any]], ep_rows: list[dict[str, Any]], tasks: list[str],
                columns: dict[str, list[Any]], image_stats: dict[str, _Stats], frames: int) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    meta = root / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
    ep_schema = pa.schema([
        ("episode_index", pa.int64()), ("tasks", pa.list_(pa.string())), ("length", pa.int64()),
        ("data/chunk_index", pa.int64()), ("data/file_index", pa.int64()), ("dataset_from_index", pa.int64()),
        ("dataset_to_index", pa.int64()), ("meta/episodes/chunk_index", pa.int64()),
        ("meta/episodes/file_index", pa.int64()), ("aermani/task_id", pa.string()),
        ("aermani/vehicle_id", pa.string()), ("aermani/backend", pa.string()), ("aermani/variant", pa.string()),
        ("aermani/state", pa.string()), ("aermani/message", pa.string()), ("aermani/started_ns", pa.int64()),
        ("aermani/ended_ns", pa.int64()), ("judge/success", pa.bool_()), ("judge/verdict", pa.string())])
    pq.write_table(pa.Table.from_pylist(ep_rows, schema=ep_schema), root / EPISODES_PATH)
    pq.write_table(_tasks_table(tasks), meta / "tasks.parquet")
    stats: dict[str, Any] = {k: _vector_stats(np.array(v, dtype=np.float64)) for k, v in columns.items()}
    for key, st in image_stats.items():
        if key in feats and st.n:
            stats[key] = st.result(frames)
    (meta / "stats.json").write_text(json.dumps(stats, indent=1, allow_nan=False), encoding="utf-8")
    info = {
        "codebase_version": CODEBASE_VERSION, "robot_type": ROBOT_TYPE, "fps": FPS,
        "total_episodes": len(ep_rows), "total_frames": frames, "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": DATA_FILES_SIZE_IN_MB,
        "video_files_size_in_mb": 200, "data_path": DATA_PATH, "video_path": None,
        "splits": {"train": f"0:{len(ep_rows)}"}, "features": feats,
    }
    (meta / "info.json").write_text(json.dumps(info, indent=2), encoding="utf-8")
