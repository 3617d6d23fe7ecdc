"""Perception: obj_localization and placement_localization from RGB-D frames (AERMANI-VLM section III)."""
