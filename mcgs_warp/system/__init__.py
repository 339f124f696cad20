"""The SLAM system: run configuration, the online loop, offline refinement, outputs."""
