"""Segmentation of the photo: GrabCut seeded by a pose, and the vehicle's region with no hint."""
