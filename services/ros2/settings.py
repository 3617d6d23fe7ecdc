"""Settings of the ROS 2 bridge (env AERMANI_ROS2_*)."""

from __future__ import annotations

from pydantic import AliasChoices, Field, SecretStr
from pydantic_settings import SettingsConfigDict

from shared.settings import ServiceSettings


class Ros2Settings(ServiceSettings):
    """ROS 2 bridge configuration (AERMANI_ROS2_*). The bridge runs when `aermani up` is asked for it
    (AERMANI_ROS2_ENABLED=1 or `--services ...,ros2`)."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_ROS2_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    enabled: bool = False
    """Start the bridge with `aermani up` (read by the launcher; the service itself always bridges)."""
    domain_id: int = Field(0, ge=0, le=232, validation_alias=AliasChoices("domain_id", "ROS_DOMAIN_ID",
                                                                          "AERMANI_ROS2_DOMAIN_ID"))
    """ROS domain id (ROS_DOMAIN_ID, as every ROS 2 node reads it): the first part of every rmw_zenoh key."""
    namespace: str = Field("/", pattern=r"^/([A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*)?$")
    """Namespace of the bridge's ROS 2 node (its topics are absolute: /<vehicle>/...)."""
    images: bool = True
    """Bridge the colour and depth images (about 10 MB/s at 640x480 and 15 fps, which the router carries
    twice: off leaves calibration, tf, pose and the rest)."""
    gateway_url: str = "http://127.0.0.1:8080/api/v1"
    """The gateway's API root: a task started from ROS 2 goes through it like any other (its token, its task
    store and audit, the page shows it), never straight to the reasoner."""
    gateway_token: SecretStr | None = Field(None, validation_alias=AliasChoices("gateway_token",
                                                                                "AERMANI_GATEWAY_TOKEN"))
    """Bearer token of the gateway (environment only; never logged)."""
    start_timeout_s: float = Field(15.0, gt=0, le=120)
    """How long a ROS 2 start_task call waits for the gateway's answer (which waits for the reasoner's)."""
    health_period_s: float = Field(1.0, gt=0)
    """How often health/ros2 is published, seconds."""

    @property
    def node_name(self) -> str:
        """The ROS 2 node's name (letters, digits and underscores: a vehicle id's '-' becomes '_')."""
        return "aermani_" + self.vehicle_id.replace("-", "_")
