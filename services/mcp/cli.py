"""`aermani mcp`: serve the MCP server over stdio (for a client that starts it) or streamable HTTP."""

from __future__ import annotations

import sys
from typing import Annotated, Any

import typer

from services.mcp.settings import McpSettings
from shared.errors import ConfigError


def register(app: typer.Typer) -> None:
    @app.command("mcp")
    def mcp_cmd(
        transport: Annotated[str | None, typer.Option(help="stdio or http (default AERMANI_MCP_TRANSPORT, stdio)")]
        = None,
        port: Annotated[int | None, typer.Option(help="HTTP port (default AERMANI_MCP_PORT, 8766)")] = None,
        gateway: Annotated[str | None, typer.Option(help="Gateway API root (default AERMANI_MCP_GATEWAY_URL)")]
        = None,
    ) -> None:
        """Model Context Protocol server: agents start, follow and abort tasks, see the camera (tasks, not raw
        flight). Gateway token from AERMANI_GATEWAY_TOKEN; HTTP needs AERMANI_MCP_TOKEN (no start without)."""
        from services.mcp.server import build_server, http_app

        options = (("transport", transport), ("port", port), ("gateway_url", gateway))
        overrides: dict[str, Any] = {k: v for k, v in options if v is not None}
        settings = McpSettings(**overrides)
        try:
            settings.check_safe()
        except ConfigError as exc:  # a clear refusal, not a traceback
            print(f"aermani mcp: {exc}", file=sys.stderr)
            raise typer.Exit(2) from None
        if settings.transport == "stdio":
            build_server(settings).run("stdio")
            return
        import uvicorn

        print(f"aermani MCP server on http://{settings.host}:{settings.port}/mcp -> {settings.gateway_url}",
              file=sys.stderr)
        uvicorn.run(http_app(settings), host=settings.host, port=settings.port, log_level="warning")
