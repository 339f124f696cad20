import pytest

from mcgs_warp.data.synthetic import generate


@pytest.fixture(scope="session")
def synthetic_seq(tmp_path_factory):
    """Three-camera synthetic sequence, 9 frames (0.15 m apart)."""
    return generate(tmp_path_factory.mktemp("ba") / "seq", n_cameras=3, n_frames=9, seed=1, progress=False)
