"""Geometry: the camera and its rays, ray/shape intersections, bounds, SDFs, per-ray sampling."""
