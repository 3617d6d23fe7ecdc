"""Entry point: `python -m services.autopilot_bridge`."""

from services.autopilot_bridge.bridge import run
from services.autopilot_bridge.settings import BridgeSettings
from shared.service import main_for


def main() -> None:
    main_for("autopilot_bridge", run, BridgeSettings, announce_at_start=False)


if __name__ == "__main__":
    main()
