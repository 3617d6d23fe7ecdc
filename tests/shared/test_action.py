"""The action protocol when the server dies: a running goal fails with ServerLost as soon as the server's
liveliness token disappears, not at the goal's timeout."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import anyio
import pytest

from shared.action import skill_client
from shared.bus import Bus
from shared.errors import ServerLost
from shared.messages import SkillRequest

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]


async def test_a_killed_server_fails_the_running_goal_at_once(router: str) -> None:
    server = subprocess.Popen([sys.executable, "-m", "tests.shared.slow_executor", router], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    bus = await Bus.open(connect=[router])
    try:
        assert server.stdout is not None and server.stdout.readline().strip() == "ready"
        async with skill_client(bus, "am1") as client:
            await anyio.sleep(0.3)
            goal = await client.send_goal(SkillRequest(skill="forward", task_id="t-1", step=1), ready_timeout=30)
            assert goal.accepted
            assert await goal.result(timeout=0.5) is None  # running: no result yet
            server.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            with pytest.raises(ServerLost, match="executor of am1 stopped"):
                await goal.result(timeout=120)  # the goal's own timeout is far away
            print(f"server loss noticed after {time.monotonic() - killed:.2f} s")
            with pytest.raises(ServerLost):
                await goal.next_feedback(timeout=0.1)
        assert not bus._watches  # a closed client leaves no liveliness subscriber behind
    finally:
        if server.poll() is None:
            server.kill()
        server.wait()
        await bus.close()
