"""Settings of the MCP server (env AERMANI_MCP_*): which gateway it drives and how it is reached."""

from __future__ import annotations

from typing import Literal

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from shared.errors import ConfigError
from shared.security import is_loopback_host
from shared.settings import exact_origins


class McpSettings(BaseSettings):
    """`aermani mcp`: a Model Context Protocol server that drives tasks through the gateway's HTTP API."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_MCP_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    gateway_url: str = "http://127.0.0.1:8080/api/v1"
    """The gateway's API root; every tool goes through it (its token, its task store, its envelope)."""
    gateway_token: SecretStr | None = Field(None, validation_alias=AliasChoices("gateway_token",
                                                                                "AERMANI_GATEWAY_TOKEN"))
    """Bearer token of the gateway (environment only; never logged)."""
    transport: Literal["stdio", "http"] = "stdio"
    """stdio (an MCP client starts `aermani mcp`) or http (streamable HTTP on host:port/mcp)."""
    host: str = "127.0.0.1"
    """Bind address for the HTTP transport (loopback by default; `token` is required on every address)."""
    port: int = Field(8766, ge=0, le=65535)
    """Port for the HTTP transport (8766: the recorder's live Foxglove server has the Foxglove default, 8765)."""
    token: SecretStr | None = Field(None, validation_alias=AliasChoices("token", "AERMANI_MCP_TOKEN"))
    """Bearer token MCP clients must send over HTTP (environment only, never logged). Required for the HTTP
    transport, on loopback too: the server holds the gateway token, and any local process (or a page the
    operator opens, were the Origin check wrong) could otherwise start tasks with its rights. Not used by stdio."""
    allowed_origins: list[str] = []
    """Browser origins allowed to call the HTTP transport, each exactly `scheme://host[:port]` (no wildcard, no
    path): a request with an `Origin` header not in this list gets 403. Empty (the default): every request that
    carries an Origin, `null` included, is refused; MCP clients that are not web pages send none."""
    allow_skills: bool = False
    """Also offer `run_skill` (one skill outside a task). Off by default: agents drive tasks, not raw motion;
    the gateway must allow it too (AERMANI_GATEWAY_SKILL_API) and the executor's envelope still applies."""
    request_timeout_s: float = Field(30.0, gt=0)
    """HTTP timeout towards the gateway."""

    @field_validator("allowed_origins")
    @classmethod
    def _exact_origins(cls, origins: list[str]) -> list[str]:
        return exact_origins(origins)

    @property
    def loopback(self) -> bool:
        return is_loopback_host(self.host)

    @property
    def lends_gateway_token(self) -> bool:
        """Whether the gateway token goes with this server's calls: over stdio (the client started this process
        and holds its environment) or over HTTP to a client that sent AERMANI_MCP_TOKEN."""
        return self.transport == "stdio" or self.token is not None

    def check_safe(self) -> None:
        """Refuse the HTTP transport without a token, on any address (loopback too)."""
        if self.transport != "http" or self.token is not None:
            return
        where = "is not loopback" if not self.loopback else "is loopback, but every local process reaches it"
        raise ConfigError(f"the MCP server over HTTP needs AERMANI_MCP_TOKEN (AERMANI_MCP_HOST={self.host} {where}): "
                          "set it in the environment, e.g. AERMANI_MCP_TOKEN=$(openssl rand -hex 24), and give it "
                          "to the MCP client as `Authorization: Bearer <token>`; or use the stdio transport")
