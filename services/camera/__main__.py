"""Entry point: `python -m services.camera`."""

from __future__ import annotations

from services.camera.service import run
from services.camera.settings import CameraSettings
from shared.service import main_for


def main() -> None:
    main_for("camera", run, CameraSettings)


if __name__ == "__main__":
    main()
