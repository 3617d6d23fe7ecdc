"""The reasoner: AERMANI-VLM's structured prompting, DRT/STE parsing, VLM backends and Algorithm 1."""
