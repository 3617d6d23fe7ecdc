"""The evaluation harness (`aermani eval`): task suites, whole stacks per vehicle, the ground-truth judge, metrics
and the report. An application tool that launches stacks, not a bus service (it has no `__main__`)."""
