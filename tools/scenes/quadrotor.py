"""Quadrotor hardware scene (§V-C, App. app:hardware).

A quadrotor with a downward-facing camera lands on a red box in a cluttered
arena. An open-vocabulary detector (OWL-ViT in the paper) turns each frame
into context-aware detections, "<object> <where>", e.g. "a drill on the
ground" or "a quadrotor on the red box"; :func:`detection` is the one place
that phrasing is made.

* :func:`quadrotor_nominal` — the prior experience D_e: the prompt for every
  combination of 1..4 of the unique nominal detections.
* :func:`quadrotor_calibration` — a labelled calibration set D_c: new
  placements (clutter moved around, objects moved onto the boxes) and a few
  unseen objects. The test scenarios' anomalous detections are
  held out of it.
* :data:`QUADROTOR_SCENARIOS` — the paper's test scenarios, with the
  expected verdict and fallback choice.

Observations list detections in a canonical order (the nominal detection
order, then known anomalous ones, then anything else as given), so a scene
that matches a cached combination yields exactly the cached text.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

from .base import Domain, Label, Sample

TASK = "landing on the red box"
ON_GROUND = "on the ground"
ON_RED_BOX = "on the red box"
ON_BLUE_BOX = "on the blue box"
MAX_CACHE_DETECTIONS = 4

#: The slow reasoner's options, by index: 0 continues, 1..2 are recovery regions.
QUADROTOR_CHOICES = ("continue", "alternative landing site", "holding zone")


def detection(label: str, where: str = ON_GROUND) -> str:
    """A context-aware detection string: ``detection("a drill")`` -> "a drill on the ground"."""
    return f"{label} {where}"


LANDING_SITES = (detection("a red box"), detection("a blue box"))
CLUTTER = tuple(
    detection(obj)
    for obj in (
        "a bicycle tire",
        "a soccer ball",
        "a drill",
        "a quadrotor",
        "a traffic cone",
        "a toolbox",
        "a skateboard",
        "a tripod",
    )
)
#: The unique detections of the nominal scene, in cache order.
NOMINAL_DETECTIONS = LANDING_SITES + CLUTTER

#: Objects never seen in the nominal scene, introduced for calibration.
UNSEEN_OBJECTS = ("a backpack", "a laptop", "a water bottle", "a cardboard box", "a chair")
#: Objects moved onto the boxes for calibration (obstructions).
OBSTRUCTING_OBJECTS = (
    "a soccer ball",
    "a drill",
    "a traffic cone",
    "a toolbox",
    "a bicycle tire",
    "a skateboard",
    "a backpack",
    "a cardboard box",
)
CALIBRATION_ANOMALIES = tuple(detection(o) for o in UNSEEN_OBJECTS) + tuple(
    detection(o, where) for where in (ON_RED_BOX, ON_BLUE_BOX) for o in OBSTRUCTING_OBJECTS
)
#: Anomalous detections of the test scenarios; never in the calibration set.
SCENARIO_ANOMALIES = (
    detection("a quadrotor", ON_RED_BOX),
    detection("a quadrotor", ON_BLUE_BOX),
    detection("a keyboard"),
)

QUADROTOR = Domain.build(
    name="quadrotor",
    robot=(
        "a vision-based autonomous quadrotor with a downward-facing camera "
        "operating in a cluttered flight arena"
    ),
    subject="quadrotor",
    tasks=(TASK,),
    nominal={"landing sites": LANDING_SITES, "ground clutter": CLUTTER},
    anomalous=CALIBRATION_ANOMALIES + SCENARIO_ANOMALIES,
    observation_size=(1, MAX_CACHE_DETECTIONS),
    default_sizes=(300, 100),
    canonical_order=True,
)

_ORDER = {d: i for i, d in enumerate(NOMINAL_DETECTIONS + QUADROTOR.anomalous)}


def canonical(detections: Iterable[str]) -> tuple[str, ...]:
    """Detections without repeats, in cache order; unknown ones last, as given."""
    unique = list(dict.fromkeys(detections))
    return tuple(sorted(unique, key=lambda d: _ORDER.get(d, len(_ORDER))))


def quadrotor_sample(detections: Iterable[str], label: Label = "nominal") -> Sample:
    """A labelled sample built exactly as the cache entries are."""
    return QUADROTOR.sample(TASK, canonical(detections), label)


def quadrotor_observation(detections: Iterable[str]) -> str:
    """The text to embed (the full prompt) for a frame's detections."""
    return quadrotor_sample(detections).text


def quadrotor_nominal(max_detections: int = MAX_CACHE_DETECTIONS) -> tuple[Sample, ...]:
    """D_e: one nominal sample per combination of 1..``max_detections`` nominal detections.

    Ordered by combination size, then :func:`itertools.combinations` order.
    """
    from itertools import combinations

    return tuple(
        quadrotor_sample(combo)
        for r in range(1, max_detections + 1)
        for combo in combinations(NOMINAL_DETECTIONS, r)
    )


def _object(d: str) -> str:
    for where in (ON_GROUND, ON_RED_BOX, ON_BLUE_BOX):
        if d.endswith(" " + where):
            return d[: -len(where) - 1]
    return d


def _box_of(d: str) -> str | None:
    if d.endswith(ON_RED_BOX):
        return LANDING_SITES[0]
    if d.endswith(ON_BLUE_BOX):
        return LANDING_SITES[1]
    return None


def _calibration_anomaly(rng: random.Random) -> tuple[str, ...]:
    """1-2 anomalous detections among 2..4 in all, physically consistent: an
    object is in one place only, and a box with something on it is in view."""
    anomalies = [rng.choice(CALIBRATION_ANOMALIES)]
    if rng.random() < 0.25:
        others = [a for a in CALIBRATION_ANOMALIES if _object(a) != _object(anomalies[0])]
        anomalies.append(rng.choice(others))
    moved = {_object(a) for a in anomalies}
    boxes = [b for a in anomalies if (b := _box_of(a)) is not None]
    core = list(dict.fromkeys(anomalies + boxes))
    free = [d for d in NOMINAL_DETECTIONS if _object(d) not in moved and d not in core]
    size = max(len(core), rng.randint(2, MAX_CACHE_DETECTIONS))
    return tuple(core + rng.sample(free, size - len(core)))


def quadrotor_calibration(
    seed: int = 0, *, n_nominal: int = 120, n_anomaly: int = 120
) -> tuple[Sample, ...]:
    """D_c: labelled calibration frames, deterministic by ``seed``.

    Like the cache, a frame shows at most four detections (the camera's
    field of view over the arena). Nominal frames re-place the clutter, which
    yields the same detection strings; anomalous frames add a few unseen
    objects or move objects onto the boxes (obstructions), about three in
    four of them obstructions. Nominal samples come first, then anomalies.
    """
    rng = random.Random(f"aesop:quadrotor:{seed}:calibration")
    nominal = [
        quadrotor_sample(
            rng.sample(NOMINAL_DETECTIONS, rng.randint(1, MAX_CACHE_DETECTIONS)), "nominal"
        )
        for _ in range(n_nominal)
    ]
    anomalies = [quadrotor_sample(_calibration_anomaly(rng), "anomaly") for _ in range(n_anomaly)]
    return tuple(nominal + anomalies)


@dataclass(frozen=True)
class QuadrotorScenario:
    """A hardware test scenario: what the detector sees and what should happen."""

    name: str
    detections: tuple[str, ...]
    expected_anomaly: bool
    expected_choice: str
    description: str = ""

    def __post_init__(self) -> None:
        if self.expected_choice not in QUADROTOR_CHOICES:
            raise ValueError(f"expected_choice must be one of {QUADROTOR_CHOICES}")

    @property
    def expected_index(self) -> int:
        """The expected option index y (0 = continue)."""
        return QUADROTOR_CHOICES.index(self.expected_choice)

    @property
    def text(self) -> str:
        """The prompt the fast detector embeds for this scenario."""
        return quadrotor_observation(self.detections)

    def sample(self) -> Sample:
        return quadrotor_sample(self.detections, "anomaly" if self.expected_anomaly else "nominal")


def _scenarios(items: Sequence[QuadrotorScenario]) -> Mapping[str, QuadrotorScenario]:
    return MappingProxyType({s.name: s for s in items})


QUADROTOR_SCENARIOS: Mapping[str, QuadrotorScenario] = _scenarios(
    (
        QuadrotorScenario(
            name="nominal",
            detections=(
                detection("a red box"),
                detection("a bicycle tire"),
                detection("a soccer ball"),
                detection("a drill"),
            ),
            expected_anomaly=False,
            expected_choice="continue",
            description="Clutter on the ground only; the red box is free. Land normally.",
        ),
        QuadrotorScenario(
            name="quadrotor_on_red_box",
            detections=(
                detection("a red box"),
                detection("a blue box"),
                detection("a quadrotor"),
                detection("a quadrotor", ON_RED_BOX),
            ),
            expected_anomaly=True,
            expected_choice="alternative landing site",
            description=(
                "Another quadrotor has landed on the red box (a quadrotor on the ground is "
                "nominal clutter, one on the landing site is not); divert to the blue box."
            ),
        ),
        QuadrotorScenario(
            name="both_boxes_occupied",
            detections=(
                detection("a red box"),
                detection("a blue box"),
                detection("a quadrotor", ON_RED_BOX),
                detection("a quadrotor", ON_BLUE_BOX),
            ),
            expected_anomaly=True,
            expected_choice="holding zone",
            description="Quadrotors occupy both boxes; divert to the holding zone.",
        ),
        QuadrotorScenario(
            name="keyboard_on_ground",
            detections=(
                detection("a red box"),
                detection("a keyboard"),
                detection("a bicycle tire"),
                detection("a drill"),
            ),
            expected_anomaly=True,
            expected_choice="continue",
            description="An unseen keyboard on the ground: anomalous but inconsequential.",
        ),
    )
)
