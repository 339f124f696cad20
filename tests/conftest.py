import os

import warp as wp
from hypothesis import settings

wp.config.log_level = wp.LOG_WARNING
wp.init()

# With CI set (as CI services and .ci/run's callers do), Hypothesis draws the same examples
# on every run and keeps no example database, so a red CI run reproduces locally with
# `CI=true python -m pytest -q tests`. Settings the tests build (test_fuzz.SETTINGS)
# inherit from the profile loaded here.
settings.register_profile("mcgs-ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("mcgs-ci")
