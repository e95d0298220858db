"""SemanticKITTI class ids and the material ids of synthetic surfaces."""
from __future__ import annotations

from enum import IntEnum


class Label(IntEnum):
    """SemanticKITTI raw label ids used by the synthetic city."""

    UNLABELED = 0
    CAR = 10
    ROAD = 40
    PARKING = 44
    SIDEWALK = 48
    OTHER_GROUND = 49
    BUILDING = 50
    FENCE = 51
    LANE_MARKING = 60
    VEGETATION = 70
    TRUNK = 71
    TERRAIN = 72
    POLE = 80
    TRAFFIC_SIGN = 81


class Mat(IntEnum):
    """How an object's surface is coloured (see camera shading) and reflects (LiDAR)."""

    FACADE = 0  # building wall with windows
    WALL = 1  # plain wall
    POLE = 2
    SIGN = 3
    TRUNK = 4
    FOLIAGE = 5
    CAR = 6  # car body
    CABIN = 7  # car cabin (glass with pillars)
    FENCE = 8
    LAMP = 9  # street-light head (emissive at night)


# Instance ids live in the upper 16 bits of a label (label & 0xFFFF is the class).
INSTANCE_SHIFT = 16
