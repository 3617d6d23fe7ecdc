"""Entry point: `python -m services.gateway`."""

import sys

from pydantic import ValidationError

from services.gateway.service import run
from services.gateway.settings import GatewaySettings, check_safe
from shared.errors import ConfigError
from shared.service import main_for


def main() -> None:
    # Check before anything opens: an unsafe bind must fail fast with a readable message, not a traceback.
    try:
        check_safe(GatewaySettings())
    except (ConfigError, ValidationError) as exc:
        print(f"gateway: {exc}", file=sys.stderr)
        sys.exit(2)
    main_for("gateway", run, GatewaySettings)


if __name__ == "__main__":
    main()
