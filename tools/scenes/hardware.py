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

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from shared.messages import Detection, Observation

from . import quadrotor_calibration, quadrotor_nominal
from .quadrotor import ON_BLUE_BOX, ON_RED_BOX, canonical, detection

if TYPE_CHECKING:  # the client is the caller's; the scene's texts need no HTTP stack
    from services.embedding.client import EmbeddingClient
    from services.embedding.schemas import CacheInfo, Calibrated

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


def camera_observation(text: str, seq: int, robot: str, task: str = "landing on the red box"
                       ) -> Observation:
    """The camera's observation of a scene written by :func:`observation_text`: its text
    and, one per line, its detections."""
    return Observation(robot=robot, seq=seq, task=task, text=text,
                       detections=detections_of(text.splitlines()))


def detections_of(phrases: Sequence[str]) -> tuple[Detection, ...]:
    """The camera's detections: "a drill on the ground" -> label "a drill", where "on the
    ground"."""
    return tuple(Detection(label=d.rsplit(" on ", 1)[0], where="on " + d.rsplit(" on ", 1)[1])
                 if " on " in d else Detection(label=d) for d in phrases)


async def build_scene_cache(client: EmbeddingClient, name: str, *, model: str | None = None,
                            say: Callable[[str], None] = lambda _: None,
                            max_detections: int = 4, alpha: float = 0.95
                            ) -> tuple[CacheInfo, Calibrated]:
    """The hardware scene's nominal cache over REST, each experience with its detections,
    calibrated split-conformal at ``alpha`` on the nominal frames of the scene's
    calibration set (``quadrotor_calibration``; its anomalies give the AUROC), top-1
    scores. A verdict on an observation with detections is then the combined p-value of
    the whole observation and its worst detection. A cache kept from an earlier run with
    the scene's experiences is reused as it is (with the scenes it learned since: proposals
    accepted from the slow reasoner's "continue")."""
    scenes = [s.concepts for s in quadrotor_nominal(max_detections)]
    info = await client.create_cache(name, model=model, k=1)
    if info.size and (info.size < len(scenes) or not info.detections):
        raise ValueError(f"cache {name!r} holds {info.size} experiences and "
                         f"{info.detections} detections, not the {len(scenes)} scenes of the "
                         "hardware scene: remove it (or the data dir) first")
    if not info.size:
        say(f"building the nominal cache: {len(scenes)} combinations of up to "
            f"{max_detections} detections")
        await client.add_items(name, [
            {"text": observation_text(seen),
             "detections": [d.model_dump(exclude_none=True) for d in detections_of(seen)]}
            for seen in scenes], background=True)
    rows = quadrotor_calibration(seed=0)
    cal = await client.calibrate(
        name, "conformal", alpha=alpha,
        calibration=[(observation_text(s.concepts), s.label == "anomaly") for s in rows],
        detections=[detections_of(s.concepts) for s in rows])
    say(f"calibrated: conformal at alpha {alpha} on {cal.n} nominal frames, tau = "
        f"{cal.threshold:.4f}, AUROC {cal.auroc or 0:.3f} (whole observations)")
    return await client.cache(name), cal
