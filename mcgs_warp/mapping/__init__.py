"""Gaussian mapping (paper §III-B): the map, its losses, optimizer, densification, refinement."""
