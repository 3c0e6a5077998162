"""The paper's hardware scenarios (Sec. V-C) as observation scripts for a downward camera.

Each :class:`DemoScenario` reports its nominal clutter throughout and its
anomalous detections while the robot is within ``seen_within_m``
(horizontally) of their spot. A quadrotor on the red box comes into view as
the robot nears the landing area (in 2b the landing area's report names both
boxes' occupants, as the paper's scene had them in view together); the
keyboard lies on the ground along the way and leaves the view behind the
robot. :func:`observation_text` writes one detection per line, in canonical
order: the text the vector cache holds and the reasoner quotes line by line.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import quadrotor_calibration, quadrotor_nominal
from .quadrotor import ON_BLUE_BOX, ON_RED_BOX, canonical, detection

GOAL = "red-box"  # the nominal landing site: the scenario's goal


@dataclass(frozen=True)
class DemoScenario:
    name: str
    expected: str  # where the flight must end: GOAL or a region name
    expected_decision: str | None  # the reasoner's choice (an option label); None: no anomaly
    clutter: tuple[str, ...]  # nominal detections, seen throughout
    anomalies: tuple[str, ...] = ()  # seen while the robot is near ``spot``
    spot: tuple[float, float] | None = None  # m, (x, y) of the anomalous objects
    seen_within_m: float = 1.2  # m: horizontal distance from which the camera sees them
    description: str = ""

    def detections(self, position: Sequence[float]) -> tuple[str, ...]:
        """What the camera reports with the robot at ``position`` (m, x y z)."""
        visible = bool(self.anomalies) and self.spot is not None and float(np.hypot(
            position[0] - self.spot[0], position[1] - self.spot[1])) <= self.seen_within_m
        return canonical(self.clutter + (self.anomalies if visible else ()))


RED, BLUE = detection("a red box"), detection("a blue box")
RED_BOX_SPOT = (2.8, 0.0)  # the hardware scene's goal
KEYBOARD_SPOT = (0.0, 0.0)  # on the ground, under the way in
SCENARIOS: tuple[DemoScenario, ...] = (
    DemoScenario("1-nominal", GOAL, None,
                 (RED, detection("a bicycle tire"), detection("a soccer ball"),
                  detection("a drill")),
                 description="clutter on the ground only: land on the red box"),
    DemoScenario("2a-quadrotor-on-red-box", "blue-box", "alternative landing site",
                 (RED, BLUE, detection("a quadrotor")),
                 (detection("a quadrotor", ON_RED_BOX),), RED_BOX_SPOT,
                 description="another quadrotor on the red box: land on the blue box"),
    DemoScenario("2b-both-boxes-occupied", "holding-zone", "holding zone",
                 (RED, BLUE),
                 (detection("a quadrotor", ON_RED_BOX), detection("a quadrotor", ON_BLUE_BOX)),
                 RED_BOX_SPOT,
                 description="quadrotors on both boxes: hold in the holding zone"),
    DemoScenario("3-keyboard-on-ground", GOAL, "continue",
                 (RED, detection("a bicycle tire"), detection("a drill")),
                 (detection("a keyboard"),), KEYBOARD_SPOT,
                 description="an unseen keyboard on the ground under the way in: anomalous "
                             "but inconsequential; land on the red box"),
)


def observation_text(detections: Sequence[str]) -> str:
    """The observation o_t: one detection per line, in the cache's canonical order."""
    return "\n".join(canonical(detections))


def nominal_texts(max_detections: int = 4) -> list[str]:
    """D_e: every combination of 1..``max_detections`` nominal detections, as observation
    texts (4, the hardware appendix's, gives 385)."""
    return [observation_text(s.concepts) for s in quadrotor_nominal(max_detections)]


def calibration_set(seed: int = 0) -> list[dict[str, str]]:
    """D_c: labelled frames for the TPR-0.9 threshold of the hardware appendix."""
    return [{"text": observation_text(s.concepts), "label": s.label}
            for s in quadrotor_calibration(seed=seed)]
