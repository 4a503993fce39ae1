"""Cameras, the paper's pose parameters, the search coordinates and image windows."""
