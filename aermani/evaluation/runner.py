"""Runs evaluation episodes on the real stack: K simulated vehicles on one router, one worker per vehicle.

Per episode: `sim/reset` lays out the task's scenario (vehicle on the ground, disarmed), `reasoner/start_task`
starts the command, every `reasoner/step` of that task is kept, the terminal `reasoner/task_status` ends it,
and `sim/judge` gives the ground-truth verdict. Each finished episode is appended to episodes.jsonl at once,
so an interrupted run resumes where it stopped (finished episode ids are skipped).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shlex
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import BaseModel, ConfigDict, model_validator

from aermani.evaluation.accounting import effective_settings, masked
from aermani.evaluation.provenance import source_revision
from aermani.evaluation.records import RESULTS_FILE, EpisodeRecord, ResultsFile
from aermani.evaluation.scoring import accepted_objects, score_episode
from aermani.evaluation.tasks import (
    DEFAULT_SEEDS_PER_LINE,
    DEFAULT_SPLIT,
    DEFAULT_T_MAX_S,
    EpisodeSpec,
    check_split,
    expand,
    group_by_suite,
    load_jsonl,
    load_suites,
)
from aermani.launcher import OPTIONAL, PER_VEHICLE, Stack, available_services, free_udp_port
from shared.action import skill_client
from shared.bus import Bus, Subscription, query_ready
from shared.errors import AermaniError, BusError, ConfigError
from shared.keys import Keys
from shared.messages import (
    Abort,
    GripperCommand,
    GripperState,
    JudgeRequest,
    JudgeResult,
    LandedState,
    SkillRequest,
    TaskRequest,
    VehicleState,
    new_id,
    now_ns,
)
from shared.tasks import REFUSED_BEFORE_TAKEOFF, follow_task, judge_episode

log = logging.getLogger("aermani.evaluation")

STATUS_MARGIN_S = 90.0  # wait this long past T_max for the reasoner's own timeout status before giving up
START_RETRY_S = 30.0  # a vehicle may still be finishing its previous task: retry start_task this long
QUERY_TIMEOUT_S = 20.0
TAKEOFF_ATTEMPTS = 3  # a trial whose take-off fails before the policy ever acts is restarted, as on a real rig
READY_WAIT_S = 60.0  # a service's liveliness token appears before its queryables: wait for them this long


class RunConfig(BaseModel):
    """Everything `aermani eval` needs; the CLI builds it from its options."""

    model_config = ConfigDict(extra="forbid")

    out: Path = Path("runs/eval")
    backend: str = "rules"
    output_mode: str = "auto"
    """Answer decoding of the reasoner (AERMANI_REASONER_OUTPUT_MODE): auto, schema or text."""
    variants: list[str] = ["full"]
    paper_history: bool = False
    """The paper's History only (AERMANI_REASONER_PAPER_HISTORY): each step's DRT and action, no live detections
    or world map."""
    free_text_baselines: bool = False
    """The unstructured and ReAct baselines decoded as free text (AERMANI_REASONER_FREE_TEXT_BASELINES)."""
    model: str = ""
    base_url: str | None = None
    api_key: str | None = None
    episodes: int | None = None
    """Episodes per suite cycling through its lines (opt-in; some lines may not run)."""
    seeds_per_line: int | None = None
    """Every line of each suite on this many layouts (episodes = lines x seeds); overrides `episodes`. With neither
    set, the built-in suites run every line on DEFAULT_SEEDS_PER_LINE layouts and a task file each line once."""
    split: str = DEFAULT_SPLIT
    """Built-in suites' split: dev (work against it) or test (held out; headline figures only)."""
    suites: list[str] | None = None
    tasks_file: Path | None = None
    seed: int = 0
    parallel: int = 1
    speed_factor: float = 4.0
    t_max_s: float = DEFAULT_T_MAX_S
    # Use vehicles already running behind a router (e.g. on other hosts) instead of launching a stack.
    connect: str | None = None
    vehicles: list[str] | None = None
    startup_timeout_s: float = 240.0
    extra_env: dict[str, str] = {}
    progress: bool = True
    # Perception segmenter of every vehicle: color (real computer vision on the rendered pixels, the default),
    # sam3, or sim (the simulator's ground-truth masks: an oracle, not perception). Named in the report.
    segmenter: str = "color"
    # Simulator realism: realistic (depth noise, exposure, pose drift, indoor air; the default), harsh or ideal.
    realism: str = "realistic"
    # What the backend is, stated at the top of the report (e.g. "numbers reflect the local test server").
    note: str = ""
    # Testing hook: stop (as if interrupted) after this many episodes have finished in this run.
    stop_after: int | None = None

    @model_validator(mode="after")
    def _every_line_by_default(self) -> RunConfig:
        if self.episodes is None and self.seeds_per_line is None and self.tasks_file is None:
            self.seeds_per_line = DEFAULT_SEEDS_PER_LINE
        return self

    def command_line(self) -> str:
        """The `aermani eval` command that reproduces this run, every option that shapes the numbers explicit
        (defaults included, so a later change of a default does not change what the line means)."""
        args = ["aermani", "eval", "--split", self.split, "--backend", self.backend, "--variant",
                ",".join(self.variants)]
        if self.model:
            args += ["--model", self.model]
        if self.base_url:
            args += ["--base-url", self.base_url]
        if self.tasks_file is not None:
            args += ["--tasks", str(self.tasks_file)]
        if self.suites:
            args += ["--suites", ",".join(self.suites)]
        if self.seeds_per_line is not None:
            args += ["--seeds-per-line", str(self.seeds_per_line)]
        elif self.episodes is not None:
            args += ["--episodes", str(self.episodes)]
        args += ["--seed", str(self.seed), "--segmenter", self.segmenter, "--realism", self.realism,
                 "--speed-factor", f"{self.speed_factor:g}", "--t-max", f"{self.t_max_s:g}",
                 "--output-mode", self.output_mode]
        args += ["--paper-history"] if self.paper_history else []
        args += ["--free-text-baselines"] if self.free_text_baselines else []
        if self.connect:
            args += ["--connect", self.connect, "--vehicles", ",".join(self.vehicle_ids())]
        else:
            args += ["--parallel", str(self.parallel)]
        if self.note:
            args += ["--note", self.note]
        return shlex.join([*args, "--out", str(self.out)])

    def vehicle_ids(self) -> list[str]:
        if self.vehicles:
            return list(self.vehicles)
        return [f"ev{i + 1}" for i in range(max(1, self.parallel))]


def episode_specs(cfg: RunConfig) -> list[EpisodeSpec]:
    if cfg.tasks_file is not None:
        tasks = group_by_suite(load_jsonl(cfg.tasks_file))
        if cfg.suites:
            tasks = {s: t for s, t in tasks.items() if s in cfg.suites}
        # A user's file lists its episodes; --episodes only repeats them when asked for more.
        return expand(tasks, episodes=cfg.episodes, backends=[cfg.backend], variants=cfg.variants,
                      base_seed=cfg.seed, seeds_per_line=cfg.seeds_per_line)
    return expand(load_suites(cfg.suites, split=check_split(cfg.split)), episodes=cfg.episodes,
                  backends=[cfg.backend], variants=cfg.variants, base_seed=cfg.seed,
                  seeds_per_line=cfg.seeds_per_line)


# The MAVLink UDP ports every simulated vehicle gets for itself (free ports, bound when its environment is made).
PORT_KEYS = ("AERMANI_SIM_API_PORT", "AERMANI_SIM_API_LOCAL_PORT", "AERMANI_SIM_GCS_PORT", "AERMANI_SIM_GCS_LOCAL_PORT",
             "AERMANI_AUTOPILOT_BRIDGE_CONNECTION")


def run_env(cfg: RunConfig) -> dict[str, str]:
    """The settings a run gives every vehicle's services (the backend, the world, the segmenter), ports aside."""
    env = {
        "AERMANI_SIM_SPEED_FACTOR": str(cfg.speed_factor),
        "AERMANI_REASONER_BACKEND": cfg.backend,
        "AERMANI_REASONER_OUTPUT_MODE": cfg.output_mode,
        "AERMANI_REASONER_PAPER_HISTORY": str(cfg.paper_history).lower(),
        "AERMANI_REASONER_FREE_TEXT_BASELINES": str(cfg.free_text_baselines).lower(),
        "AERMANI_REASONER_T_MAX_S": str(cfg.t_max_s),
        "AERMANI_PERCEPTION_SEGMENTER": cfg.segmenter,
        "AERMANI_RECORDER_SEGMENTATION": "1" if cfg.segmenter == "sim" else "0",
        "AERMANI_SIM_REALISM": cfg.realism,
    }
    if cfg.model:
        env["AERMANI_REASONER_MODEL"] = cfg.model
    if cfg.base_url:
        env["AERMANI_REASONER_BASE_URL"] = cfg.base_url
    if cfg.api_key:
        env["AERMANI_REASONER_API_KEY"] = cfg.api_key
    return {**env, **cfg.extra_env}


def vehicle_env(cfg: RunConfig) -> dict[str, str]:
    """Environment of one simulated vehicle's services: its own MAVLink UDP ports and the run's settings."""
    api, api_local, gcs, gcs_local = (str(free_udp_port()) for _ in range(4))
    ports = dict(zip(PORT_KEYS, (api, api_local, gcs, gcs_local, f"udpin:127.0.0.1:{api}"), strict=True))
    return {**ports, **run_env(cfg)}


# The services of one evaluated vehicle. Episodes are judged in the simulator's world: its camera, never a
# configured camera service.
PER_VEHICLE_SERVICES = [s for s in PER_VEHICLE if s not in OPTIONAL]


def build_stack(cfg: RunConfig, vehicle_ids: list[str]) -> Stack:
    services = [s for s in available_services() if s in PER_VEHICLE_SERVICES]
    missing = [s for s in PER_VEHICLE_SERVICES if s not in services]
    if missing:
        raise ConfigError(f"the evaluation needs every per-vehicle service; missing in this checkout: {missing}")
    stack = Stack(services, vehicle_id=vehicle_ids[0], env=vehicle_env(cfg), log_dir=cfg.out / "logs")
    for vid in vehicle_ids[1:]:
        stack.add_vehicle(vid, services, vehicle_env(cfg))
    return stack


# --------------------------------------------------------------------------- one vehicle


@dataclass
class VehicleWorker:
    """Runs episodes one after another on one vehicle id."""

    bus: Bus
    vehicle_id: str
    cfg: RunConfig
    keys: Keys = field(init=False)
    state: Subscription[VehicleState] = field(init=False)

    def __post_init__(self) -> None:
        self.keys = Keys(self.vehicle_id)
        self.state = self.bus.subscribe(self.keys.autopilot_state, maxsize=2)

    def close(self) -> None:
        self.state.close()

    async def _current_state(self, timeout: float = 10.0) -> VehicleState | None:
        latest = self.state.latest_nowait()
        try:
            return await self.state.recv(timeout=timeout)
        except TimeoutError:
            return latest

    async def _land(self, timeout: float = 90.0) -> None:
        """Land and let PX4 auto-disarm before the next reset, as between real trials: teleporting an armed,
        flying vehicle would leave the bridge's offboard stream and PX4's mode out of step."""
        st = await self._current_state()
        if st is None or st.landed_state not in (LandedState.IN_AIR, LandedState.TAKEOFF, LandedState.LANDING):
            return
        if st.gripper == GripperState.CLOSED or st.gripper_holding:
            await self._empty_gripper()
        deadline = time.monotonic() + timeout
        async with skill_client(self.bus, self.vehicle_id) as skills:
            try:
                goal = await skills.send_goal(SkillRequest(skill="land"), timeout=QUERY_TIMEOUT_S,
                                              ready_timeout=READY_WAIT_S)
            except AermaniError as exc:
                log.warning("%s: land request failed (%s); resetting anyway", self.vehicle_id, exc)
                return
            if not goal.accepted:
                log.warning("%s: land rejected (%s); resetting anyway", self.vehicle_id, goal.reason)
                return
            await goal.result(timeout)
        while time.monotonic() < deadline:  # PX4 disarms a couple of seconds after touchdown
            st = await self._current_state(timeout=2.0)
            if st is not None and not st.armed:
                return
        log.warning("%s: vehicle still armed %.0f s after land; resetting anyway", self.vehicle_id, timeout)

    async def _empty_gripper(self) -> None:
        """The previous episode (already judged) ended with an object in the gripper: open it before landing, as
        an operator takes the object out between real trials. A vehicle carrying an object under it cannot
        touch down, so its land would time out and the next reset would find it armed."""
        try:
            res = await query_ready(self.bus, self.keys.autopilot_command, GripperCommand(action="open"),
                                    timeout=QUERY_TIMEOUT_S, ready_timeout=READY_WAIT_S)
        except AermaniError as exc:
            log.warning("%s: could not open the gripper before landing (%s)", self.vehicle_id, exc)
            return
        if not res.ok:
            log.warning("%s: gripper open refused before landing: %s", self.vehicle_id, res.message)
        await asyncio.sleep(1.0)  # let the object fall clear before descending

    async def _wait_grounded(self, since_ns: int, timeout: float = 30.0) -> None:
        """After a reset the bridge must report the vehicle on the ground, disarmed, before a task starts, from a
        HEARTBEAT received after the reset (`since_ns`): its armed flag and mode are those of PX4's last
        HEARTBEAT (1 Hz), so a state from before it still shows the previous episode's end (an AUTO.LAND, or
        OFFBOARD after a crash stopped the motors), and the next takeoff would read the reset's mode change as
        PX4 taking the vehicle from the stack."""
        self.state.latest_nowait()  # anything queued predates the reset
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                st = await self.state.recv(timeout=max(0.1, deadline - time.monotonic()))
            except TimeoutError:
                break
            if (not st.armed and st.landed_state in (LandedState.ON_GROUND, LandedState.UNKNOWN) and st.link_ok
                    and st.last_heartbeat_ns >= since_ns):
                return
        log.warning("%s: vehicle not reported grounded %.0f s after reset; starting anyway", self.vehicle_id,
                    timeout)

    async def _world(self) -> JudgeResult | None:
        """The simulator's ground truth now (objects, surfaces, its clock); None when it does not answer (the
        record then lacks what it would have told, and says so)."""
        try:
            return await query_ready(self.bus, self.keys.sim_judge, JudgeRequest(op="world"), timeout=QUERY_TIMEOUT_S,
                                     ready_timeout=READY_WAIT_S)
        except AermaniError as exc:
            log.warning("%s: the simulator's world query failed (%s)", self.vehicle_id, exc)
            return None

    async def run(self, spec: EpisodeSpec) -> EpisodeRecord:
        task = spec.task
        t_max = task.t_max_s or self.cfg.t_max_s
        rec = EpisodeRecord(episode_id=spec.episode_id, suite=task.suite, backend=spec.backend,
                            variant=spec.variant, model=self.cfg.model, task=task, seed=spec.seed,
                            vehicle_id=self.vehicle_id, t_max_s=t_max)
        restarts: list[str] = []
        for attempt in range(1, TAKEOFF_ATTEMPTS + 1):
            try:
                out = await self._run(spec, rec, t_max)
            except (AermaniError, TimeoutError) as exc:
                log.warning("%s: episode %s could not run: %s", self.vehicle_id, spec.episode_id, exc)
                return rec.model_copy(update={"harness_error": f"{type(exc).__name__}: {exc}",
                                              "ended_ns": now_ns(), "attempts": attempt, "restarts": restarts})
            if not _failed_before_first_step(out):
                return out.model_copy(update={"attempts": attempt, "restarts": restarts})
            restarts.append(f"attempt {attempt}: {out.state} before the first reasoning step: {out.message}")
            log.warning("%s: episode %s failed before its first reasoning step (%s); attempt %d of %d",
                        self.vehicle_id, spec.episode_id, out.message, attempt, TAKEOFF_ATTEMPTS)
        # The trial never reached the policy: not a policy failure, so it stays out of the metrics (and a
        # rerun tries it again), but the report lists it.
        return out.model_copy(update={"attempts": TAKEOFF_ATTEMPTS, "restarts": restarts, "harness_error":
                                      f"failed before the first reasoning step {TAKEOFF_ATTEMPTS} times: "
                                      f"{out.message}"})

    async def _run(self, spec: EpisodeSpec, rec: EpisodeRecord, t_max: float) -> EpisodeRecord:
        task = spec.task
        await self._land()
        reset = await query_ready(self.bus, self.keys.sim_reset, task.scenario(spec.seed), timeout=QUERY_TIMEOUT_S,
                                  ready_timeout=READY_WAIT_S)
        if not reset.ok:
            return rec.model_copy(update={"harness_error": f"sim/reset refused the scenario: {reset.message}"})
        # The simulator's reset notice clears the executor's working memory (services/executor/memory.py,
        # world_reset): the episode starts from an empty memory without restarting any process.
        await self._wait_grounded(since_ns=now_ns())
        before = await self._world()  # the simulated clock and the world a choice is decided in, at the start
        accepted, undecided = accepted_objects(task, before)
        if undecided:
            return rec.model_copy(update={"harness_error": undecided})
        task_id = new_id("ev-")
        request = TaskRequest(command=task.command, task_id=task_id, variant=spec.variant, t_max_s=t_max,
                              takeoff=True)
        started = now_ns()
        followed = await follow_task(self.bus, self.keys, request, timeout=t_max + STATUS_MARGIN_S,
                                     ready_timeout=READY_WAIT_S, retry_rejected_s=START_RETRY_S)
        if not followed.accept.accepted:
            return rec.model_copy(update={"harness_error": f"reasoner refused the task: {followed.accept.reason}",
                                          "task_id": task_id})
        status, steps, foreign = followed.final, followed.steps, followed.foreign
        ended = now_ns()
        after = await self._world()  # the simulated clock at the end, before the judge waits for a rest
        if status is None:
            # The reasoner never ended the task: stop it so the next episode starts clean.
            self.bus.publish(self.keys.abort, Abort(reason="evaluation: no terminal status", source="evaluation",
                                                    task_id=task_id))

        v = await judge_episode(self.bus, self.keys, accepted, task.destination, timeout=QUERY_TIMEOUT_S)
        judge, judged_ok = v.result, v.success
        state = status.state.value if status else "timeout"
        # Success needs both: the task's own end state (the policy finished it before T_max) and the judge.
        success, verdict = success_verdict(state, judged_ok, v.message, t_max)
        if task.expect == "not_found":
            # The world lacks the object: the right answer is to say so, in bounded steps, holding nothing.
            success, verdict = not_found_verdict(state, status.message if status else "", len(steps),
                                                 task.not_found_max_steps, judge.held)
            judged_ok = judge.held is None
        # Scored for what it asks: the commanded motions from the trajectory, the choice's decision and how it
        # was made (aermani/evaluation/scoring.py).
        success, verdict, scores = score_episode(task, steps, before, judge.held, success, verdict)
        return rec.model_copy(update={**scores,
            "task_id": task_id, "state": state,
            "message": status.message if status else f"no terminal status within {t_max + STATUS_MARGIN_S:.0f} s",
            "success": success, "judge_success": judged_ok, "verdict": verdict, "held": judge.held,
            "collisions": judge.collisions,
            "steps": steps, "status": status, "judge": judge, "started_ns": started, "ended_ns": ended,
            "sim_started_s": before.sim_time_s if before else None,
            "sim_ended_s": after.sim_time_s if after else None,
            "foreign_samples": foreign,
        })


def success_verdict(state: str, judged_ok: bool, judge_message: str, t_max: float) -> tuple[bool, str]:
    """(success, verdict): the judge must find the world right AND the task must have ended `succeeded`."""
    if state == "succeeded":
        return judged_ok, judge_message
    if state == "timeout":
        return False, f"{judge_message}; the task did not end before T_max ({t_max:.0f} s)"
    if judged_ok:
        return False, f"{judge_message}, but the task ended {state}, not succeeded"
    return False, judge_message


NOT_FOUND_REASON = "not found"
"""How a task's end message starts when the policy ends it because the object is not there."""


def not_found_verdict(state: str, message: str, steps: int, max_steps: int, held: str | None) -> tuple[bool, str]:
    """(success, verdict) of a task whose object the world lacks (EvalTask.expect == "not_found")."""
    if state != "failed" or not message.lower().startswith(NOT_FOUND_REASON):
        return False, (f"the world lacks the object, but the task ended {state} ({message or 'no message'}) instead "
                       "of failing with a not-found reason")
    if steps > max_steps:
        return False, f"said not found, but only after {steps} reasoning steps (bound {max_steps})"
    if held:
        return False, f"said not found while holding the {held}"
    return True, f"said not found after {steps} reasoning steps (bound {max_steps}): {message}"


def _failed_before_first_step(rec: EpisodeRecord) -> bool:
    """A take-off failure before the policy ever ran (a stack problem: the trial restarts). A command the
    policy refused is its answer: a failed episode like any other, never restarted or excluded."""
    return (rec.status is not None and rec.status.state.value == "failed" and rec.status.steps == 0
            and not rec.steps and not rec.success and not rec.status.message.startswith(REFUSED_BEFORE_TAKEOFF))


# --------------------------------------------------------------------------- the run


@dataclass
class RunSummary:
    """Outcome of one evaluation run: where it wrote, episodes planned, skipped and run, and their records."""

    out: Path
    planned: int
    skipped: int
    ran: int
    records: list[EpisodeRecord]
    interrupted: bool = False
    wall_s: float = 0.0


async def run_episodes(bus: Bus, specs: list[EpisodeSpec], cfg: RunConfig, results: ResultsFile,
                       on_done: Callable[[EpisodeRecord], None] | None = None) -> list[EpisodeRecord]:
    """One worker per vehicle pulls episodes from a shared queue until it is empty (or stop_after is hit)."""
    queue: asyncio.Queue[EpisodeSpec] = asyncio.Queue()
    for s in specs:
        queue.put_nowait(s)
    done: list[EpisodeRecord] = []
    stop = asyncio.Event()

    async def worker(vid: str) -> None:
        w = VehicleWorker(bus, vid, cfg)
        try:
            while not stop.is_set():
                try:
                    spec = queue.get_nowait()
                except asyncio.QueueEmpty:
                    return
                rec = await w.run(spec)
                results.append(rec)
                done.append(rec)
                if on_done:
                    on_done(rec)
                if cfg.stop_after is not None and len(done) >= cfg.stop_after:
                    stop.set()
        finally:
            w.close()

    async with asyncio.TaskGroup() as tg:
        for vid in cfg.vehicle_ids():
            tg.create_task(worker(vid))
    return done


def run(cfg: RunConfig) -> RunSummary:
    """Run (or resume) an evaluation and write its report; blocking. Ctrl-C stops after saving what finished."""
    from aermani.evaluation.report import write_report

    cfg.out.mkdir(parents=True, exist_ok=True)
    run_config = run_config_of(cfg)
    (cfg.out / "run_config.json").write_text(json.dumps(run_config, indent=2))  # a report rebuilt mid-run
    results = ResultsFile(cfg.out / RESULTS_FILE)
    specs = episode_specs(cfg)
    finished = results.finished_ids()
    todo = [s for s in specs if s.episode_id not in finished]
    summary = RunSummary(cfg.out, planned=len(specs), skipped=len(specs) - len(todo), ran=0, records=[])
    t0 = time.monotonic()
    if todo:
        vehicle_ids = cfg.vehicle_ids()[:len(todo)]
        cfg = cfg.model_copy(update={"vehicles": vehicle_ids})
        stack = None
        try:
            if cfg.connect:
                endpoint = cfg.connect
            else:
                stack = build_stack(cfg, vehicle_ids)
                stack.start(wait=True, timeout=cfg.startup_timeout_s)
                endpoint = stack.endpoint
            summary.records = asyncio.run(_run_async(endpoint, todo, cfg, results, len(specs),
                                                     len(specs) - len(todo)))
        except KeyboardInterrupt:
            summary.interrupted = True
        finally:
            if stack is not None:
                stack.stop()
    summary.ran = len(summary.records)
    summary.wall_s = time.monotonic() - t0
    summary.interrupted = summary.interrupted or (cfg.stop_after is not None and summary.ran < len(todo))
    write_report(cfg.out, config=run_config)
    return summary


def shell_settings(environ: Mapping[str, str], extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """Every AERMANI_* variable the services inherit from the shell (and the run's extra environment): they
    change what the services do, so the run's record names them all, those the run overrides included
    (`overridden_settings`). A secret's value is never recorded (only that it was set)."""
    return masked({**environ, **(extra or {})})


def overridden_settings(cfg: RunConfig, environ: Mapping[str, str]) -> list[str]:
    """The shell's AERMANI_* variables the run sets itself (its own settings and each vehicle's ports): the
    services never see the shell's value of these."""
    own = set(PORT_KEYS) | set(run_env(cfg))
    return sorted(k for k in environ if k.startswith("AERMANI_") and k in own)


def run_config_of(cfg: RunConfig) -> dict:
    """run_config.json: the settings (no API key), the source revision, every AERMANI_* variable of the shell, the
    run's own, the effective values of the settings that shape the numbers, and the command that reproduces it."""
    doc = cfg.model_dump(mode="json", exclude={"api_key", "extra_env", "stop_after", "progress"})
    doc.update(source_revision())
    doc["environment"] = shell_settings(os.environ, cfg.extra_env)
    doc["environment_overridden"] = overridden_settings(cfg, os.environ)
    doc["run_environment"] = masked(run_env(cfg))
    doc["effective"] = effective_settings({**os.environ, **run_env(cfg)})
    if cfg.connect:  # the vehicles were started elsewhere: these are what this shell would have given them
        doc["effective"]["note"] = "computed from this shell; the vehicles behind --connect were started elsewhere"
    doc["command"] = cfg.command_line()
    doc["report_only_command"] = shlex.join(["aermani", "eval", "--out", str(cfg.out), "--report-only"])
    return doc


async def _run_async(endpoint: str, todo: list[EpisodeSpec], cfg: RunConfig, results: ResultsFile, total: int,
                     skipped: int) -> list[EpisodeRecord]:
    try:
        bus = await Bus.open(connect=[endpoint])
    except BusError as exc:
        raise ConfigError(f"cannot reach the router at {endpoint}: {exc}")
    try:
        if not cfg.progress:
            return await run_episodes(bus, todo, cfg, results)
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        from shared.text import terminal_text

        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("{task.fields[sr]}"), TimeElapsedColumn()) as progress:
            bar = progress.add_task(f"eval {cfg.backend} on {len(cfg.vehicle_ids())} vehicle(s)", total=total,
                                    completed=skipped, sr="")
            wins = [0, 0]

            def on_done(rec: EpisodeRecord) -> None:
                wins[0] += rec.success
                wins[1] += 1
                mark = "[green]ok[/green]" if rec.success else ("[yellow]not run[/yellow]" if rec.harness_error
                                                               else "[red]fail[/red]")
                progress.console.print(f"{mark} {terminal_text(rec.episode_id)} ({terminal_text(rec.vehicle_id)}, "
                                       f"{len(rec.steps)} steps, {rec.duration_s:.0f} s): "
                                       f"{terminal_text(rec.verdict or rec.harness_error)}")
                progress.update(bar, advance=1, sr=f"success {wins[0]}/{wins[1]}")

            return await run_episodes(bus, todo, cfg, results, on_done)
    finally:
        with contextlib.suppress(Exception):
            await bus.close()
