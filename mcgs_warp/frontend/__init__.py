"""Front end: correspondences (flow), depth priors and keyframe selection."""
