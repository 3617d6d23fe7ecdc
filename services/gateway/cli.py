"""`aermani task "<command>"`: start a task through the gateway and print its steps as they happen."""

from __future__ import annotations

import json
import os
from typing import Annotated

import typer

from shared.text import plain_text


def register(app: typer.Typer) -> None:
    @app.command()
    def task(
        command: Annotated[str, typer.Argument(help="Natural-language command, e.g. 'pick up the red cup'.")],
        url: Annotated[str, typer.Option(help="Gateway base URL.")] = "http://127.0.0.1:8080",
        vehicle: Annotated[str | None, typer.Option(help="Vehicle id (default: the gateway's choice).")] = None,
        follow: Annotated[bool, typer.Option(help="Follow the event stream until the task ends.")] = True,
    ) -> None:
        """Start a task on the gateway (token from AERMANI_GATEWAY_TOKEN) and follow its reasoning steps."""
        import httpx

        token = os.environ.get("AERMANI_GATEWAY_TOKEN", "")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        body = {"command": command, **({"vehicle_id": vehicle} if vehicle else {})}
        with httpx.Client(base_url=url.rstrip("/") + "/api/v1", headers=headers, timeout=30) as c:
            try:
                r = c.post("/tasks", json=body)
            except httpx.HTTPError as exc:
                typer.echo(f"cannot reach the gateway at {url}: {exc}", err=True)
                raise typer.Exit(1)
            if r.status_code != 202:
                typer.echo(f"refused ({r.status_code}): {plain_text(r.json().get('detail', r.text))}", err=True)
                raise typer.Exit(1)
            created = r.json()
            typer.echo(plain_text(f"task {created['task_id']} on {created['vehicle_id']}"))
            if not follow:
                return
            state = "?"
            with c.stream("GET", created["links"]["events"].removeprefix("/api/v1"), timeout=None) as s:
                event = ""
                for line in s.iter_lines():
                    if line.startswith("event:"):
                        event = line[6:].strip()
                    elif line.startswith("data:"):
                        data = json.loads(line[5:])
                        if event == "step":
                            ste = data.get("ste") or {}
                            arg = f"({ste['argument']})" if ste.get("argument") else ""
                            why = (data.get("drt") or {}).get("reasoning") or ""
                            # The model's text and the services' messages are data: no escape reaches the terminal.
                            typer.echo(plain_text(f"  step {data['step']}: {ste.get('skill', 'no valid answer')}{arg} "
                                                  f"-> {data.get('skill_state') or '...'}  {why[:100]}"))
                        elif event == "task_status":
                            state = data["state"]
                            if state not in ("pending", "running"):
                                typer.echo(plain_text(f"{state}: {data.get('message', '')}"))
            raise typer.Exit(0 if state == "succeeded" else 1)
