"""Entry point: `python -m services.reasoner`."""

from services.reasoner.service import run
from services.reasoner.settings import ReasonerSettings
from shared.service import main_for


def main() -> None:
    main_for("reasoner", run, ReasonerSettings)


if __name__ == "__main__":
    main()
