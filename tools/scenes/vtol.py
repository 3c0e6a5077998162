"""VTOL urban air taxi domain — the hardest synthetic domain (§V-A, App. ap:prompting).

A vertical takeoff and landing aircraft flies toward a set destination or
lands on a designated building. Observations hold flying objects, landing
zones and ground regions. Anomalies are nuanced shifts of nominal concepts:
"a flying bird" is nominal, "a large swarming flock of birds" is not; "a
rooftop helipad" is nominal, "an icy rooftop helipad" is not. Most anomalous
concepts below are written as a small change to a nominal one, so they lie
close to the nominal experiences in embedding space.
"""

from __future__ import annotations

from .base import Domain

TASKS = ("flying toward a set destination", "landing on a designated building")

FLYING_OBJECTS = (
    "a flying bird",
    "a small flock of birds",
    "a seagull gliding",
    "a pigeon",
    "a commercial airliner at high altitude",
    "a passenger jet on approach to the airport",
    "a small private plane",
    "a helicopter",
    "a news helicopter",
    "a police helicopter",
    "another air taxi",
    "another air taxi on final approach",
    "a small delivery drone",
    "a quadcopter drone",
    "a hot air balloon in the distance",
    "a blimp",
    "a paraglider in the distance",
    "a medical helicopter on approach",
)

LANDING_ZONES = (
    "a helipad",
    "a rooftop helipad",
    "a hospital helipad",
    "a vertiport landing pad",
    "a rooftop landing pad with lit markings",
    "a landing pad with a windsock",
    "a designated landing building",
    "a flat building rooftop",
    "a parking garage rooftop",
    "an empty vertiport",
    "a charging station on the vertiport",
    "ground crew at the edge of the vertiport",
)

GROUND_REGIONS = (
    "a city park",
    "a downtown street",
    "a residential neighborhood",
    "a highway",
    "a bridge",
    "a river",
    "a lake",
    "a frozen pond",
    "a harbor with boats",
    "a railway line",
    "a stadium",
    "a football field",
    "a golf course",
    "a parking lot",
    "a shopping mall",
    "an industrial area",
    "a construction site",
    "a construction crane",
    "a tall skyscraper",
    "a radio tower",
    "a landfill",
    "a forest",
)

ANOMALOUS = (
    # Flying objects: a nominal flying object, shifted.
    "a large swarming flock of birds",
    "a large flock of birds",
    "a flock of geese at rooftop height",
    "a diving bird of prey",
    "a pigeon near the rotor",
    "a low-flying commercial airliner",
    "a small private plane below the rooftops",
    "a fighter jet at low altitude",
    "a helicopter over the landing pad",
    "a news helicopter over the vertiport",
    "another air taxi on a collision course",
    "a delivery drone over the landing pad",
    "a swarm of drones",
    "a hot air balloon near the landing building",
    "a low-flying weather balloon",
    "a paraglider in the flight path",
    # Landing zones: a nominal landing zone, shifted.
    "an icy helipad",
    "an icy rooftop helipad",
    "a snow-covered landing pad",
    "a flooded building rooftop",
    "a building rooftop on fire",
    "an unlit helipad",
    "a landing pad with faded markings",
    "a cracked landing pad",
    "a helicopter on the helipad",
    "an occupied vertiport landing pad",
    "ground crew on the landing pad",
    "people on the landing pad",
    "debris on the vertiport",
    "a landing pad with a torn windsock",
    # Ground regions: a nominal ground region, shifted.
    "a smoke-filled downtown street",
    "a collapsed bridge",
    "a flooded highway",
    "a swinging construction crane",
    "a radio tower with its warning lights out",
)

ANOMALOUS_COMBINATIONS = (
    # Two users of the same pad.
    ("a hospital helipad", "a medical helicopter on approach"),
    ("a vertiport landing pad", "another air taxi on final approach"),
    # A crane next to the landing building.
    ("a designated landing building", "a construction crane"),
    # Landfills draw birds: a bird-strike setting.
    ("a small flock of birds", "a landfill"),
    # A drone loitering near the pad.
    ("a rooftop helipad", "a quadcopter drone"),
)

VTOL = Domain.build(
    name="vtol",
    robot=(
        "a vision-based autonomous vertical takeoff and landing (VTOL) aircraft "
        "operating as an urban air taxi"
    ),
    subject="VTOL",
    tasks=TASKS,
    nominal={
        "flying objects": FLYING_OBJECTS,
        "landing zones": LANDING_ZONES,
        "ground regions": GROUND_REGIONS,
    },
    anomalous=ANOMALOUS,
    anomalous_combinations=ANOMALOUS_COMBINATIONS,
    # The paper's set has 18400 scenarios; 5000 keeps benchmarks quick.
    default_sizes=(4000, 1000),
)
