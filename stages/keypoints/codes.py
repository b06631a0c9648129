"""Keypoint type codes (the authors', stages/INTERFACES.md) and the order of the class heatmaps."""

ENDPOINT, JUNCTION, CORNER = 1, 3, 5
TYPE_CODES = (ENDPOINT, JUNCTION, CORNER)  # channels 1, 2, 3 of the heatmaps, in this order
