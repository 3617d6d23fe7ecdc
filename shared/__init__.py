"""aermani shared package: the message contract, the Zenoh key space, the asyncio bus and service plumbing."""

__version__ = "0.1.0"
