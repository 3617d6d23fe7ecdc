"""Entry point: `python -m services.executor`."""

from services.executor.service import run
from services.executor.settings import ExecutorSettings
from shared.service import main_for


def main() -> None:
    main_for("executor", run, ExecutorSettings, announce_at_start=False)


if __name__ == "__main__":
    main()
