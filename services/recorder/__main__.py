"""Entry point: `python -m services.recorder`."""

from services.recorder.service import run
from services.recorder.settings import RecorderSettings
from shared.service import main_for


def main() -> None:
    # `alive/recorder` only once the subscription is declared: a sample published after the token appears is
    # recorded (the fault suite counts on it when it checks the log across a recorder restart).
    main_for("recorder", run, RecorderSettings, announce_at_start=False)


if __name__ == "__main__":
    main()
