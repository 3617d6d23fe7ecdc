"""Entry point: `python -m services.sim` (the MAVLink vehicle starts before Zenoh has any peer)."""

from __future__ import annotations

import functools

from services.sim.app import build, run
from services.sim.settings import SimSettings
from shared.service import main_for
from shared.settings import setup_logging


def main() -> None:
    # The vehicle must answer MAVLink even while the Zenoh router is unreachable (opening a client
    # session waits for it), so the MAVLink thread starts here, before main_for opens the bus.
    settings = SimSettings()
    setup_logging(settings.log_level, "sim")
    core, server = build(settings)
    server.start()
    # "alive" is announced by run() once sim/judge and sim/reset answer.
    main_for("sim", functools.partial(run, core=core, server=server), SimSettings, settings=settings,
             announce_at_start=False)


if __name__ == "__main__":
    main()
