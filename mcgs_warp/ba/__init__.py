"""Multi-camera bundle adjustment (MCBA) and joint depth-scale alignment (JDSA), paper §III-A."""
