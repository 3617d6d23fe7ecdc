"""Settings of the recorder (env AERMANI_RECORDER_*)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import SettingsConfigDict

from shared.security import is_loopback_host
from shared.settings import ServiceSettings, exact_origins


class RecorderSettings(ServiceSettings):
    """Recorder configuration (AERMANI_RECORDER_*): the key expression to record and where MCAP files go."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_RECORDER_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    key_expr: str = "aermani/**"
    """Key expression to record. The recorder is a ground-station service: the default takes every vehicle."""
    segmentation: bool = False
    """Also record the simulator's segmentation images (`camera/@segmentation` of every vehicle: the ground
    truth the oracle segmenter reads). Its verbatim chunk keeps it out of `key_expr`'s `**`, so without this
    they are neither recorded nor rendered for the recorder; the launchers turn it on with the `sim` segmenter,
    whose masks a replay needs."""
    frame_max_hz: float = Field(1.0, ge=0)
    """Colour+depth pairs recorded per vehicle and second, at most (0: every frame). Frames are most of a log
    (a realistic depth PNG is ~240 kB): at 1 Hz an hour of task loop stays under 2 GB (docs/performance.md).
    The frame each reasoning step was decided on is kept whatever the rate (services/recorder/throttle.py)."""
    out_dir: str = "runs/recordings"
    """Directory the MCAP files go to (created when missing)."""
    file_prefix: str = "aermani"
    """File names are <prefix>-<YYYYmmdd-HHMMSS>-<index>.mcap."""
    chunk_size: int = Field(1 << 20, ge=4096)
    """MCAP chunk size in bytes. A crash loses at most the chunk in progress, so keep it modest."""
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    """Chunk compression."""
    flush_key_expr: str = "aermani/v1/*/reasoner/**"
    """After a sample on these keys (reasoning steps, task statuses, approvals: small and rare), finish the chunk
    in progress at once, so a SIGKILL or a full disk never takes a task event the writer already had with the
    chunk (frames still fill big chunks). Empty: only full chunks are written."""
    rotate_mb: float = Field(2048.0, ge=0)
    """Start a new file when the current one reaches this size in MiB (0: never by size)."""
    rotate_s: float = Field(0.0, ge=0)
    """Start a new file after this many seconds (0: never by time)."""
    queue_size: int = Field(20000, ge=10)
    """Samples the bus subscription may hold before it drops (counted in health)."""
    max_backlog_mb: float = Field(1024.0, gt=0)
    """Bytes waiting for the writer thread before new samples are dropped (counted), MiB."""
    health_period_s: float = Field(1.0, gt=0)
    """How often health/recorder is published, seconds."""
    stop_drain_s: float = Field(10.0, ge=0)
    """On SIGTERM, write the queued backlog for at most this long, then finish the file (the rest is counted
    as dropped). With the file's finish, well inside compose's 30 s stop grace for the recorder."""
    retry_s: float = Field(5.0, gt=0)
    """After a write error (disk full, unwritable path), wait this long before opening a new file."""
    foxglove: bool = False
    """Also serve the live stream to the Foxglove app over the Foxglove WebSocket protocol (services/recorder/
    live.py, which checks Origin and the token; foxglove-sdk's own server checks neither)."""
    foxglove_host: str = "127.0.0.1"
    """Address of the Foxglove WebSocket server; anything but loopback requires `foxglove_token`."""
    foxglove_port: int = Field(8765, ge=0, le=65535)
    """Port of the Foxglove WebSocket server."""
    foxglove_token: SecretStr | None = None
    """Token a Foxglove client must present (`ws://host:port/?token=...`; environment only, never logged). Unset:
    loopback only, where any local process can read the bus anyway."""
    foxglove_allowed_origins: list[str] = []
    """Web origins allowed to connect, each exactly `scheme://host[:port]` (e.g. `https://app.foxglove.dev` for
    the web app): a handshake with any other `Origin`, `null` included, gets 403. Empty (the default): only
    clients that send no Origin (not a web page)."""

    @field_validator("foxglove_allowed_origins")
    @classmethod
    def _exact_origins(cls, origins: list[str]) -> list[str]:
        return exact_origins(origins)

    @model_validator(mode="after")
    def _token_off_loopback(self) -> RecorderSettings:
        if self.foxglove and self.foxglove_token is None and not is_loopback_host(self.foxglove_host):
            raise ValueError(f"AERMANI_RECORDER_FOXGLOVE_HOST={self.foxglove_host} is not loopback: set "
                             "AERMANI_RECORDER_FOXGLOVE_TOKEN so only clients holding it see the camera and state")
        return self
