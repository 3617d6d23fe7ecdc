"""The application: what starts and composes whole stacks of services (the `aermani` CLI, the launcher and its
service catalogue, the demo, the evaluation harness, the probe's simulator frame). It sits above the services and
the contract (`shared/`), may import both, and nothing below imports it (tests/architecture/test_layers.py)."""
