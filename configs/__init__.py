"""Configuration files shipped with mcgs_warp (rigs, runs), installed as mcgs_warp.configs."""
