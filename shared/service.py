"""Service lifecycle: signals set a stop event, the bus opens, a liveliness token announces the service,
`run(bus, settings, stop)` does the work, and everything is released in `finally`."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import tempfile
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import TypeVar

from shared.bus import Bus
from shared.messages import Heartbeat
from shared.settings import ServiceSettings, setup_logging

S = TypeVar("S", bound=ServiceSettings)
RunFn = Callable[[Bus, S, asyncio.Event], Coroutine[object, object, None]]

log = logging.getLogger("aermani.service")

HEARTBEAT_PERIOD_S = 0.5


async def heartbeat(bus: Bus, settings: ServiceSettings, name: str, period_s: float = HEARTBEAT_PERIOD_S) -> None:
    """Publish `heartbeat/<name>` from the event loop itself, with how late the loop woke: a loop that hangs
    (a blocking call, a deadlock, SIGSTOP) goes quiet even though Zenoh's threads keep the liveliness token."""
    loop = asyncio.get_running_loop()
    topic, pid = settings.keys.heartbeat(name), os.getpid()
    due = loop.time()
    while True:
        lag = max(0.0, loop.time() - due)
        with contextlib.suppress(Exception):  # a closing bus must not end the service
            bus.publish(topic, Heartbeat(service=name, pid=pid, loop_lag_ms=round(lag * 1e3, 3),
                                               bus_dropped=bus.stats()["dropped"]))
        due = loop.time() + period_s
        await asyncio.sleep(period_s)


def announce(bus: Bus, settings: ServiceSettings, name: str) -> None:
    """Declare the liveliness token `alive/<name>`: the service is ready to answer."""
    bus.declare_token(settings.keys.alive(name))


async def serve_forever(name: str, run: RunFn[S], settings: S, stop: asyncio.Event | None = None,
                        announce_at_start: bool = True) -> None:
    """Open the bus, declare `alive/<name>`, run the service until `stop` is set or `run` returns.

    A service whose queryables need set-up first passes `announce_at_start=False` and calls `announce()`
    once they are declared, so that "alive" always means "answers"."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
    opening = asyncio.create_task(Bus.open(connect=settings.zenoh_connect, mode=settings.zenoh_mode,
                                           certs=settings.zenoh_certs or None, identity=settings.zenoh_identity))
    stopper = asyncio.create_task(stop.wait())
    await asyncio.wait({opening, stopper}, return_when=asyncio.FIRST_COMPLETED)
    if not opening.done():
        # Stopped while still waiting for the router: nothing to release.
        opening.cancel()
        log.info("%s stopped before reaching the router %s", name, settings.zenoh_connect)
        return
    stopper.cancel()
    bus = opening.result()
    bus.name = name
    beat: asyncio.Task[None] | None = None
    try:
        if announce_at_start:
            announce(bus, settings, name)
        log.info("%s up (vehicle %s, zenoh %s)", name, settings.vehicle_id, settings.zenoh_connect)
        beat = asyncio.create_task(heartbeat(bus, settings, name), name=f"{name}.heartbeat")
        runner: asyncio.Task[None] = asyncio.create_task(run(bus, settings, stop), name=f"{name}.run")
        stopper = asyncio.create_task(stop.wait(), name=f"{name}.stop")
        done, _ = await asyncio.wait({runner, stopper}, return_when=asyncio.FIRST_COMPLETED)
        if runner in done:
            stopper.cancel()
            runner.result()  # re-raise a crash so the launcher sees a non-zero exit
        else:
            runner.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(runner, 10.0)
    finally:
        if beat is not None:
            beat.cancel()
        await bus.close()
        log.info("%s stopped", name)


def die_with_parent() -> None:
    """Under the launcher (AERMANI_PARENT_PID set), ask Linux to SIGTERM this process when the launcher dies,
    and exit if it already has. Done here, after exec, because a `preexec_fn` is unsafe in a threaded parent."""
    parent = os.environ.get("AERMANI_PARENT_PID", "")
    if not parent.isdigit():
        return
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    if os.getppid() != int(parent):  # the launcher died before prctl took effect
        raise SystemExit(f"the launcher (pid {parent}) is gone; not starting")


CRASH_RESET_S = 60.0
"""A run at least this long was healthy: the next crash waits the shortest delay again."""


def crash_delay(name: str, max_s: float, ran_s: float, state_dir: str | Path | None = None) -> tuple[float, int]:
    """How long a crashed service waits before it exits, and the how-many-th crash in a row this is: 0.5 s
    doubling per crash up to `max_s`, the count kept in `state_dir` (the temporary directory: a restarted
    container keeps its own /tmp) and reset by a run of CRASH_RESET_S or longer."""
    path = Path(state_dir or tempfile.gettempdir()) / f"aermani-crashes-{name}"
    crashes = 0
    with contextlib.suppress(OSError, ValueError):
        crashes = int(path.read_text().strip() or 0)
    if ran_s >= CRASH_RESET_S:
        crashes = 0
    with contextlib.suppress(OSError):
        path.write_text(str(crashes + 1))
    return min(max_s, 0.5 * 2.0 ** min(crashes, 20)), crashes + 1


def _crash_backoff_setting() -> float:
    """AERMANI_CRASH_BACKOFF_S read without the settings class (a bad setting is one of the crashes)."""
    try:
        return min(600.0, max(0.0, float(os.environ.get("AERMANI_CRASH_BACKOFF_S", "0") or 0)))
    except ValueError:
        return 0.0


def main_for(name: str, run: RunFn[S], settings_cls: type[S], *, settings: S | None = None,
             announce_at_start: bool = True) -> None:
    """Body of every `services/<name>/__main__.py`. With AERMANI_CRASH_BACKOFF_S, a crash waits before the
    process exits (`crash_delay`), so a container engine that restarts at once does not spin."""
    die_with_parent()
    started = time.monotonic()
    try:
        settings = settings or settings_cls()
        setup_logging(settings.log_level, name)
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(serve_forever(name, run, settings, announce_at_start=announce_at_start))
    except BaseException as exc:
        if isinstance(exc, SystemExit) and exc.code in (0, None):
            raise
        max_s = _crash_backoff_setting()
        if max_s > 0:
            delay, nth = crash_delay(name, max_s, time.monotonic() - started)
            if not logging.getLogger().handlers:
                setup_logging("INFO", name)
            log.error("%s failed (%s: %s); exiting in %.1f s (crash %d in a row, AERMANI_CRASH_BACKOFF_S=%g)",
                      name, type(exc).__name__, str(exc).splitlines()[0] if str(exc) else "", delay, nth, max_s)
            with contextlib.suppress(KeyboardInterrupt):
                time.sleep(delay)
        raise
