"""Synthetic multi-view scenes with exact instance/part ground truth (rendered with mitsuba 3).

``scenes`` (recipes, pure numpy) never needs mitsuba; ``render`` imports it only when rendering.
"""

from votesplat_ns.eval.synthetic.scenes import GENERATOR_VERSION, RECIPES, Scene, make_scene

__all__ = ["GENERATOR_VERSION", "RECIPES", "Scene", "make_scene"]
