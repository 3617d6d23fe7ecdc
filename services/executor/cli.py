"""`aermani skill` and `aermani skills`: run one executor skill or list the library from the shell."""

from __future__ import annotations

import asyncio
from typing import Annotated

import typer

from shared.action import skill_client
from shared.bus import Bus
from shared.keys import Keys
from shared.messages import SkillAccept, SkillLibrary, SkillRequest, SkillStatus
from shared.settings import env_endpoints
from shared.text import plain_text


async def _run_skill(vehicle: str, skill: str, argument: str | None, timeout: float) -> SkillStatus | SkillAccept:
    bus = await Bus.open(connect=env_endpoints())
    try:
        async with skill_client(bus, vehicle) as skills:
            await asyncio.sleep(0.3)  # the status subscription reaches the router before the goal
            goal = await skills.send_goal(SkillRequest(skill=skill, argument=argument), timeout=10)
            if not goal.accepted:
                return goal.accept
            result = await goal.result(timeout)
            if result is None:
                raise SystemExit(f"no result within {timeout:.0f} s (goal {goal.goal_id})")  # printed, exit 1
            return result
    finally:
        await bus.close()


async def _library(vehicle: str) -> SkillLibrary:
    bus = await Bus.open(connect=env_endpoints())
    try:
        return await bus.query(Keys(vehicle).skills, None, timeout=10)
    finally:
        await bus.close()


def register(app: typer.Typer) -> None:
    @app.command("skill")
    def skill_cmd(
        name: Annotated[str, typer.Argument(help="skill name, e.g. forward, obj_localization")],
        argument: Annotated[str | None, typer.Argument(help="object or surface query")] = None,
        vehicle: Annotated[str, typer.Option(help="vehicle id")] = "am1",
        timeout: Annotated[float, typer.Option(help="seconds to wait for the result")] = 180.0,
    ) -> None:
        """Run one skill on the executor and print its result (router from AERMANI_ZENOH_CONNECT)."""
        res = asyncio.run(_run_skill(vehicle, name, argument, timeout))
        if isinstance(res, SkillAccept):
            typer.echo(f"rejected: {plain_text(res.reason)}")
            raise typer.Exit(2)
        typer.echo(f"{res.state.value}: {plain_text(res.message)}")
        if res.outcome.perceived:
            typer.echo(f"perceived: {plain_text(res.outcome.perceived)}")
        raise typer.Exit(0 if res.state.value == "succeeded" else 1)

    @app.command("skills")
    def skills_cmd(vehicle: Annotated[str, typer.Option(help="vehicle id")] = "am1") -> None:
        """List the executor's skill library."""
        lib = asyncio.run(_library(vehicle))
        for s in lib.skills:
            arg = f"({s.argument})" if s.argument else ""
            hidden = "" if s.policy_visible else " [operator]"
            typer.echo(plain_text(f"{s.name}{arg}{hidden}: {s.description}"))
