"""Generative objectives for action-chunk policies: one family per file behind :class:`.base.Objective`.

Objectives are chosen by name (``OBJECTIVES``), so a checkpoint's hyper-parameters stay plain strings and loading
one never calls anything a file names.
"""

from .base import Objective, TrainingTarget
from .ddpm import DDPM
from .icfm import ICFM
from .meanflow import MeanFlow
from .otcfm import OTCFM
from .reflow import Reflow
from .solvers import SOLVERS

OBJECTIVES = {"icfm": ICFM, "otcfm": OTCFM, "ddpm": DDPM, "meanflow": MeanFlow, "reflow": Reflow}


def build_objective(name: str, **options) -> Objective:
    """The objective called ``name`` (one of :data:`OBJECTIVES`), built with ``options``."""
    if name not in OBJECTIVES:
        raise ValueError(f"unknown objective {name!r}; choose one of {sorted(OBJECTIVES)}")
    try:
        return OBJECTIVES[name](**options)
    except TypeError as e:
        raise ValueError(f"bad options {options} for objective {name!r}: {e}") from None


__all__ = [
    "DDPM",
    "ICFM",
    "OBJECTIVES",
    "OTCFM",
    "SOLVERS",
    "MeanFlow",
    "Objective",
    "Reflow",
    "TrainingTarget",
    "build_objective",
]
