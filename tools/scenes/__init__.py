"""Labelled text observations for the paper's synthetic domains and hardware scene.

Domains: ``warehouse`` (WM, easiest), ``vehicle`` (AV), ``vtol`` (hardest)
and ``quadrotor`` (the hardware demonstration's landing scene). Each sample's
``text`` is the domain's prompt (App. ap:prompting) filled with a task and a
list of observed concepts; it is the string the fast reasoner embeds.
"""

from .base import (
    Dataset,
    Domain,
    Label,
    Sample,
    concept_subset,
    prompt_template,
    sample_dataset,
    write_jsonl,
)
from .quadrotor import (
    NOMINAL_DETECTIONS,
    QUADROTOR_CHOICES,
    QUADROTOR_SCENARIOS,
    QuadrotorScenario,
    detection,
    quadrotor_calibration,
    quadrotor_nominal,
    quadrotor_observation,
    quadrotor_sample,
)
from .registry import DOMAINS, generate, get_domain

__all__ = [
    "DOMAINS",
    "NOMINAL_DETECTIONS",
    "QUADROTOR_CHOICES",
    "QUADROTOR_SCENARIOS",
    "Dataset",
    "Domain",
    "Label",
    "Sample",
    "QuadrotorScenario",
    "concept_subset",
    "detection",
    "generate",
    "get_domain",
    "prompt_template",
    "quadrotor_calibration",
    "quadrotor_nominal",
    "quadrotor_observation",
    "quadrotor_sample",
    "sample_dataset",
    "write_jsonl",
]
