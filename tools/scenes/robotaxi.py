"""Autonomous Vehicle (AV) domain — intermediate difficulty (§V-A).

A robotaxi drives to a set destination. Nominal observations mix
task-relevant objects (vehicles, road users, signs and signals, road
features) with task-irrelevant ones (an airplane in the sky is nominal).
Anomalies are unusual versions of task-relevant objects (a blank speed limit
sign, a traffic light on a truck) or combinations of ordinary ones that do
not belong together (a stop sign on a multi-lane freeway).
"""

from __future__ import annotations

from .base import Domain

TASK = "driving to a set destination"

VEHICLES = (
    "a car",
    "a parked car",
    "a sedan",
    "a minivan",
    "a taxi",
    "a city bus",
    "a school bus",
    "a delivery truck",
    "a pickup truck",
    "a flatbed truck",
    "a semi-truck",
    "a garbage truck",
    "a motorcycle",
    "a police car",
    "an ambulance with its siren on",
    "a tow truck towing a car",
)

ROAD_USERS = (
    "a pedestrian on the sidewalk",
    "a pedestrian crossing at the crosswalk",
    "a person walking a dog",
    "a jogger on the sidewalk",
    "a person waiting at a bus stop",
    "a cyclist in the bike lane",
    "a person riding an electric scooter",
    "a crossing guard",
    "a construction worker in a hard hat",
    "a traffic officer signaling cars to stop",
)

TRAFFIC_CONTROL = (
    "a traffic light",
    "a red traffic light",
    "a yellow traffic light",
    "a green traffic light",
    "a stop sign",
    "a yield sign",
    "a speed limit sign",
    "a one-way sign",
    "a no parking sign",
    "a pedestrian crossing sign",
    "a school zone sign",
    "a railroad crossing sign",
)

ROAD_FEATURES = (
    "a crosswalk",
    "an intersection",
    "a roundabout",
    "a bike lane",
    "a bus stop",
    "a speed bump",
    "a lane merge",
    "a highway on-ramp",
    "a multi-lane freeway",
    "a tunnel entrance",
    "a bridge",
    "a parking lot entrance",
    "a road construction zone with orange cones",
)

TASK_IRRELEVANT = (
    "an airplane in the sky",
    "a helicopter in the sky",
    "a cloud in the sky",
    "a bird on a power line",
    "a billboard",
    "a tree",
    "a storefront",
    "an apartment building",
    "a mountain range in the distance",
    "a street lamp",
    "a mailbox",
    "a fire hydrant",
    "a park bench",
    "a flag on a pole",
    "a parked bicycle",
)

ANOMALOUS = (
    "a blank speed limit sign",
    "a traffic light on a truck",
    "a speed limit sign reading 300 mph",
    "a stop sign lying in the road",
    "a stop sign painted blue",
    "a traffic light dangling by its wires",
    "a traffic light showing red and green at once",
    "a billboard showing a giant stop sign",
    "a car driving the wrong way",
    "an overturned truck blocking the road",
    "a mattress lying in the traffic lane",
    "a fallen tree across the road",
    "a sinkhole in the road",
    "a deer standing on the road",
    "a horse-drawn carriage in the traffic lane",
    "a person in a dinosaur costume crossing the street",
    "a child chasing a ball into the street",
    "a sailboat on a trailer blocking two lanes",
    "a road sign with arrows pointing in both directions",
    "a pedestrian signal showing a car symbol",
    "a police car parked sideways across the lane",
    "a flooded underpass",
)

ANOMALOUS_COMBINATIONS = (
    # Things that do not belong on a freeway.
    ("a stop sign", "a multi-lane freeway"),
    ("a pedestrian crossing at the crosswalk", "a multi-lane freeway"),
    ("a cyclist in the bike lane", "a multi-lane freeway"),
    # Conflicting right-of-way instructions.
    ("a green traffic light", "a traffic officer signaling cars to stop"),
    ("a green traffic light", "a crossing guard"),
)

VEHICLE = Domain.build(
    name="vehicle",
    robot="a vision-based autonomous vehicle operating as a taxi service",
    subject="autonomous vehicle",
    tasks=(TASK,),
    nominal={
        "vehicles": VEHICLES,
        "road users": ROAD_USERS,
        "traffic control": TRAFFIC_CONTROL,
        "road features": ROAD_FEATURES,
        "task-irrelevant objects": TASK_IRRELEVANT,
    },
    anomalous=ANOMALOUS,
    anomalous_combinations=ANOMALOUS_COMBINATIONS,
    default_sizes=(640, 200),  # 840 scenarios, as in the paper
)
