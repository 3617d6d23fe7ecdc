"""The recorder: every sample on aermani/** into MCAP, replay, timelines and offline re-reasoning."""
