"""Warehouse Manipulator (WM) domain — the easiest synthetic domain (§V-A).

A mobile manipulator sorts objects on a conveyor belt. Nominal observations
are ordinary parcels and goods on the belt and ordinary warehouse
surroundings; anomalies are overtly abnormal (a smoking lithium battery, a
leaking bleach bottle, two forklifts in collision), so they sit far from the
nominal experiences in embedding space.
"""

from __future__ import annotations

from .base import Domain

TASK = "sorting objects on a conveyor belt"

CONVEYOR_BELT = (
    "a cardboard package",
    "a small cardboard box",
    "a large cardboard box",
    "a padded envelope",
    "a plastic mailer bag",
    "a bubble-wrapped parcel",
    "a shrink-wrapped package",
    "a package with a shipping label",
    "a boxed laptop computer",
    "a desktop computer",
    "a boxed computer monitor",
    "a boxed computer keyboard",
    "a boxed smartphone",
    "a boxed pair of headphones",
    "a boxed video game console",
    "a boxed toaster",
    "a boxed kitchen blender",
    "a hardcover book",
    "a stack of paperback books",
    "a shoebox",
    "a bag of folded clothing",
    "a children's toy in its packaging",
    "a tube-shaped poster mailer",
    "a rolled-up rug",
    "a plastic-wrapped pillow",
    "a ream of printer paper",
    "a sealed case of bottled water",
    "a sealed bottle of shampoo",
    "a plastic tote bin",
    "a box of canned food",
)

SURROUNDINGS = (
    "a storage shelf",
    "a tall pallet rack",
    "a stack of wooden pallets",
    "a forklift parked at its charging station",
    "a pallet jack",
    "a rolling cart",
    "a stack of empty totes",
    "a packing station",
    "a tape dispenser",
    "a roll of stretch wrap",
    "a barcode scanner",
    "a warehouse worker in a safety vest",
    "a worker scanning barcodes",
    "a supervisor holding a tablet",
    "another sorting robot",
    "an autonomous mobile robot carrying a shelf",
    "an overhead light",
    "a fire extinguisher mounted on the wall",
    "yellow floor markings",
    "a safety barrier",
    "a loading dock door",
    "a cardboard recycling bin",
    "a trash bin",
    # Members of the anomalous combinations below: ordinary on their own.
    "a forklift driving down the main aisle",
    "a forklift driving up the main aisle",
    "a forklift lifting a pallet to the top shelf",
    "a worker restocking the bottom of the pallet rack",
    "a delivery truck pulling away from the loading dock",
    "a pallet jack being pushed onto the dock plate",
    "a pallet of aerosol cans",
    "a maintenance worker welding a shelf bracket",
)

ANOMALOUS = (
    "a smoking lithium battery",
    "a leaking bleach bottle",
    "a broken glass bottle",
    "two forklifts in collision",
    "a package on fire",
    "a box leaking corrosive acid",
    "a hissing propane tank",
    "a puddle of spilled gasoline",
    "a loaded handgun",
    "a hand grenade",
    "a package with exposed wires and a ticking timer",
    "a live rattlesnake",
    "a cat on the conveyor belt",
    "a dead rat on the conveyor belt",
    "a person lying on the conveyor belt",
    "a worker's arm caught in the conveyor belt",
    "an overturned forklift",
    "a collapsed storage shelf",
    "a pallet of boxes toppling off the rack",
    "a sparking electrical cable",
    "thick smoke rising from a shelf",
    "a flooded warehouse floor",
    "a shattered fluorescent light tube",
    "a box leaking an unknown white powder",
    "a bag of used syringes",
    "a chainsaw with its engine running",
    "a crate of live chickens",
    "a jammed conveyor belt crushing boxes",
    "a swarm of bees escaping from a package",
    "a cracked drum labelled radioactive",
)

ANOMALOUS_COMBINATIONS = (
    # Head-on in the same aisle: the paper's "two forklifts in collision" in the making.
    ("a forklift driving down the main aisle", "a forklift driving up the main aisle"),
    # A raised load above a person.
    (
        "a forklift lifting a pallet to the top shelf",
        "a worker restocking the bottom of the pallet rack",
    ),
    # A trailer leaving while equipment rolls onto the dock plate.
    (
        "a delivery truck pulling away from the loading dock",
        "a pallet jack being pushed onto the dock plate",
    ),
    # Hot work beside pressurised flammables.
    ("a pallet of aerosol cans", "a maintenance worker welding a shelf bracket"),
)

WAREHOUSE = Domain.build(
    name="warehouse",
    robot="a vision-based autonomous mobile manipulator robot operating in a warehouse",
    subject="warehouse manipulator",
    tasks=(TASK,),
    nominal={"conveyor belt objects": CONVEYOR_BELT, "surrounding environment": SURROUNDINGS},
    anomalous=ANOMALOUS,
    anomalous_combinations=ANOMALOUS_COMBINATIONS,
    default_sizes=(1200, 351),  # 1551 scenarios, as in the paper
)
