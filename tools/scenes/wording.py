"""Held-out wordings: the synthetic domains as a new captioner would write them.

A robot's observations are written by a captioner or a VLM, and their wording changes with
each model update or camera: "a coffee mug on the worktop" becomes "mug for tea, kitchen
bench". A :class:`Captioner` rewrites a sample's detections and its brief line the way such
a change does, from rules the detector never sees in its nominal set, each concept always
the same new way:

* synonyms (a table of this module's own, word by word: "box" -> "carton", "car" ->
  "automobile"),
* articles changed or dropped ("a" -> "the", "one", none) and plurals ("two boxes"),
* reorderings ("a red box on the ground" -> "on the ground: red box"; "a red light" ->
  "light, red"),
* a captioner style for the whole line (one of :data:`STYLES`), with the task reworded by
  the same table.

Each new sample keeps its concepts and its label (a reworded anomaly is still one) and
reports the reworded phrases as its detections. Deterministic by seed; pure.
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass, replace

from .base import Dataset, Domain, Sample, sample_dataset

# word -> its held-out alternatives (none of them a word of the domains' own wording)
SYNONYMS: dict[str, tuple[str, ...]] = {
    "box": ("carton", "crate"), "boxes": ("cartons", "crates"), "boxed": ("packaged",),
    "package": ("parcel", "packet"), "cardboard": ("paperboard", "corrugated"),
    "small": ("little", "compact"), "large": ("big", "bulky"), "tall": ("high",),
    "bag": ("sack", "pouch"), "envelope": ("mailer", "letter"), "computer": ("PC",),
    "laptop": ("notebook computer",), "monitor": ("display", "screen"),
    "smartphone": ("mobile phone", "cell phone"), "headphones": ("earphones", "headset"),
    "book": ("volume",), "books": ("volumes",), "clothing": ("clothes", "garments"),
    "toy": ("plaything",), "rug": ("carpet", "mat"), "pillow": ("cushion",),
    "paper": ("sheets",), "bottle": ("flask",), "bottled": ("canned",),
    "water": ("drinking water",),
    "bin": ("container", "tub"), "food": ("groceries",), "shelf": ("shelving unit", "rack"),
    "pallet": ("skid",), "pallets": ("skids",), "wooden": ("timber", "wood"),
    "cart": ("trolley",), "worker": ("employee", "staff member"), "person": ("individual",
                                                                             "human"),
    "forklift": ("lift truck", "fork truck"), "station": ("point", "dock"),
    "truck": ("lorry", "van"), "car": ("automobile", "vehicle"), "cars": ("vehicles",),
    "sedan": ("saloon car",), "bus": ("coach",), "motorcycle": ("motorbike",),
    "pedestrian": ("walker", "passer-by"), "sidewalk": ("pavement", "footpath"),
    "crosswalk": ("zebra crossing",), "traffic": ("road",), "light": ("signal", "lamp"),
    "sign": ("signpost", "road sign"), "cyclist": ("bike rider", "bicyclist"),
    "bike": ("bicycle", "cycle"), "bicycle": ("bike", "cycle"), "tree": ("oak", "roadside tree"),
    "building": ("block", "tower"), "street": ("road",), "road": ("street",),
    "highway": ("motorway", "expressway"), "freeway": ("motorway",), "bridge": ("overpass",),
    "lot": ("area",), "airplane": ("aircraft", "plane"), "plane": ("aircraft",),
    "jet": ("airliner",), "helicopter": ("chopper", "rotorcraft"), "bird": ("songbird",),
    "birds": ("songbirds",), "drone": ("UAV",), "sky": ("air",), "cloud": ("cloudbank",),
    "rooftop": ("roof", "roof deck"), "helipad": ("heliport", "helideck"),
    "landing": ("touchdown",), "pad": ("platform", "spot"), "river": ("stream",),
    "lake": ("reservoir",), "park": ("green space", "gardens"), "ground": ("floor", "pavement"),
    "red": ("crimson", "scarlet"), "blue": ("navy", "azure"), "yellow": ("amber",),
    "green": ("lime",), "ball": ("football",), "drill": ("power drill",),
    "cone": ("pylon",), "toolbox": ("tool case", "tool chest"), "tire": ("tyre", "wheel"),
    "tripod": ("camera stand",), "skateboard": ("skate deck",), "quadrotor": ("quadcopter",),
    "conveyor": ("transport",), "belt": ("line", "band"), "objects": ("items", "goods"),
    "sorting": ("separating", "arranging"), "driving": ("travelling", "heading"),
    "flying": ("travelling", "cruising"), "destination": ("goal", "endpoint"),
    "designated": ("assigned",), "set": ("fixed", "given"), "toward": ("to",),
    "storage": ("stock",), "rack": ("racking",), "jack": ("lifter",), "vest": ("jacket",),
    "kitchen": ("cooking",), "camera": ("cam",), "dog": ("puppy",), "stop": ("halt",),
    "parking": ("car park",), "school": ("schoolhouse",), "construction": ("roadworks",),
    "city": ("urban",), "apartment": ("flat",), "lamp": ("light",), "bench": ("seat",),
}

# one line per observation: {task} and {items} (the reworded detections)
STYLES: tuple[str, ...] = (
    "Visible while {task}: {items}.",
    "Camera frame, task {task}. Objects: {items}",
    "{items} -- seen during {task}",
    "Detected {items}; the robot is {task}.",
    "Current view ({task}): {items}",
)

_PREPOSITION = re.compile(r"^(.+?) (on|in|at|with|near|beside|by) (the |a |an )?(.+)$")


def _synonyms(text: str, rng: random.Random, rate: float) -> str:
    words = text.split(" ")
    out = []
    for word in words:
        key = word.lower()
        alternatives = SYNONYMS.get(key)
        out.append(rng.choice(alternatives) if alternatives and rng.random() < rate else word)
    return " ".join(out)


def _plural(noun_phrase: str) -> str:
    head, _, last = noun_phrase.rpartition(" ")
    if last.endswith("s") or last.endswith("x") or last.endswith("ch"):
        last += "es" if not last.endswith("s") else ""
    elif last.endswith("y") and len(last) > 1 and last[-2] not in "aeiou":
        last = last[:-1] + "ies"
    else:
        last += "s"
    return f"{head} {last}".strip()


def reword_phrase(phrase: str, rng: random.Random, *, rate: float = 0.7) -> str:
    """One detection as a new captioner writes it (see the module docstring)."""
    body = re.sub(r"^(a|an|the) ", "", phrase.strip())
    body = _synonyms(body, rng, rate)
    place = ""
    found = _PREPOSITION.match(body)
    if found and rng.random() < 0.5:  # "red box on the ground" -> "on the ground: red box"
        body, place = found.group(1), f"{found.group(2)} the {found.group(4)}"
    words = body.split(" ")
    if len(words) >= 2 and rng.random() < 0.3:  # "red traffic light" -> "traffic light, red"
        body = f"{' '.join(words[1:])}, {words[0]}"
    short = len(body.split(" ")) <= 3 and "," not in body
    article = rng.choice(("a", "the", "", "one", "two") if short else ("a", "the", "", "one"))
    if article == "two":
        body = f"two {_plural(body)}"
    elif article == "a":
        body = f"{'an' if body[:1].lower() in 'aeiou' else 'a'} {body}"
    elif article:
        body = f"{article} {body}"
    if place:
        body = f"{place}: {body}" if rng.random() < 0.5 else f"{body} ({place})"
    return body


@dataclass(frozen=True)
class Captioner:
    """A new captioner: it writes each concept one way of its own (drawn once per concept
    from this module's rules) and every line in one style, as a model update does."""

    domain: Domain
    seed: int = 0
    # False: only the detections are reworded, the line keeps the robot's own template and
    # task ("The VTOL is ... and observes: a; b."), as when the detector's model changes
    # but not the code that writes the line
    lines: bool = True

    def phrase(self, concept: str) -> str:
        return reword_phrase(concept, random.Random(f"aesop:words:{self.seed}:{concept}"))

    @property
    def style(self) -> str:
        return random.Random(f"aesop:words:{self.seed}:{self.domain.name}").choice(STYLES)

    def reword(self, sample: Sample) -> Sample:
        """``sample`` with its detections and brief line in this captioner's wording (same
        label, same concepts); the paper's whole prompt (``text``) carries them too."""
        phrases = tuple(self.phrase(c) for c in sample.concepts)
        if not self.lines:
            return replace(sample, brief=self.domain.brief(sample.task, phrases),
                           text=self.domain.prompt(sample.task, phrases),
                           observation=self.domain.scene(phrases), reported=phrases)
        task = _synonyms(sample.task, random.Random(f"aesop:words:{self.seed}:{sample.task}"),
                         0.8)
        line = self.style.format(task=task, items=", ".join(phrases))
        return replace(sample, brief=line, text=self.domain.prompt(task, phrases),
                       observation=self.domain.scene(phrases), reported=phrases)


@dataclass(frozen=True)
class DriftSet:
    """A domain before and after a wording switch: the cache's nominal samples and a
    held-out nominal calibration set in the old wording; reviewed nominal scenes in the
    new wording (to accept, in order); a test set of new-wording nominal samples and
    anomalies, and the same test set as the old wording had it (what the detector does
    without drift)."""

    domain: Domain
    nominal: tuple[Sample, ...]
    calibration: tuple[Sample, ...]
    reviewed: tuple[Sample, ...]
    test: tuple[Sample, ...]
    original: tuple[Sample, ...]


def drift_set(domain: Domain, *, seed: int = 0, n_nominal: int = 600,
              n_calibration: int = 200, n_reviewed: int = 80, n_test_nominal: int = 200,
              n_anomaly: int = 100, lines: bool = True) -> DriftSet:
    """Samples of ``domain`` split as :class:`DriftSet` says, the reviewed and test ones
    reworded by one :class:`Captioner` (``lines``: its line style too; the nominal draws
    are distinct scenes)."""
    n_new = n_reviewed + n_test_nominal
    data: Dataset = sample_dataset(domain, seed=seed,
                                   n_nominal=n_nominal + n_calibration + n_new,
                                   n_anomaly=n_anomaly)
    nominal = list(data.nominal)
    random.Random(f"aesop:drift:{domain.name}:{seed}:split").shuffle(nominal)
    captioner = Captioner(domain, seed, lines)
    cut = n_nominal + n_calibration
    new = [captioner.reword(s) for s in nominal[cut:]]
    anomalies = [captioner.reword(s) for s in data.anomalies]
    return DriftSet(domain, tuple(nominal[:n_nominal]), tuple(nominal[n_nominal:cut]),
                    tuple(new[:n_reviewed]), tuple(new[n_reviewed:]) + tuple(anomalies),
                    tuple(nominal[cut + n_reviewed:]) + data.anomalies)

