"""Entry point: `python -m services.ros2`."""

from services.ros2.service import run
from services.ros2.settings import Ros2Settings
from shared.service import main_for


def main() -> None:
    main_for("ros2", run, Ros2Settings)


if __name__ == "__main__":
    main()
