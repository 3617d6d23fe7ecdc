"""Entry point: `python -m services.recorder`."""

from services.recorder.service import run
from services.recorder.settings import RecorderSettings
from shared.service import main_for


def main() -> None:
    main_for("recorder", run, RecorderSettings)


if __name__ == "__main__":
    main()
