"""Entry point: `python -m services.perception`."""

from services.perception.service import run
from services.perception.settings import PerceptionSettings
from shared.service import main_for


def main() -> None:
    main_for("perception", run, PerceptionSettings, announce_at_start=False)


if __name__ == "__main__":
    main()
