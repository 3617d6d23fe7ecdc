"""`aermani mcp`: serve the MCP server over stdio (for a client that starts it) or streamable HTTP."""

from __future__ import annotations

import sys
from typing import Annotated, Any

import typer

from services.mcp.settings import McpSettings


def register(app: typer.Typer) -> None:
    @app.command("mcp")
    def mcp_cmd(
        transport: Annotated[str | None, typer.Option(help="stdio or http (default AERMANI_MCP_TRANSPORT, stdio)")]
        = None,
        port: Annotated[int | None, typer.Option(help="HTTP port (default AERMANI_MCP_PORT, 8765)")] = None,
        gateway: Annotated[str | None, typer.Option(help="Gateway API root (default AERMANI_MCP_GATEWAY_URL)")]
        = None,
    ) -> None:
        """Model Context Protocol server: agents start, follow and abort tasks, see the camera (tasks, not raw
        flight). Gateway token from AERMANI_GATEWAY_TOKEN; HTTP clients need AERMANI_MCP_TOKEN."""
        from services.mcp.server import build_server, http_app

        options = (("transport", transport), ("port", port), ("gateway_url", gateway))
        overrides: dict[str, Any] = {k: v for k, v in options if v is not None}
        settings = McpSettings(**overrides)
        settings.check_safe()
        if settings.transport == "stdio":
            build_server(settings).run("stdio")
            return
        import uvicorn

        print(f"aermani MCP server on http://{settings.host}:{settings.port}/mcp -> {settings.gateway_url}",
              file=sys.stderr)
        if settings.token is None:
            print("no AERMANI_MCP_TOKEN: clients are not authenticated, so the gateway is called without its token "
                  "(a gateway that has one refuses them); set AERMANI_MCP_TOKEN",
                  file=sys.stderr)
        uvicorn.run(http_app(settings), host=settings.host, port=settings.port, log_level="warning")
