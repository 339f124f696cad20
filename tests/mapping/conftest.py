import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ba"))  # problems.py

from mcgs_warp.data.synthetic import generate  # noqa: E402

KEYFRAMES = [0, 2, 4, 6]
HELD_OUT = [1, 3, 5]


@pytest.fixture(scope="session")
def mapping_seq(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("mapping") / "seq", n_cameras=3, n_frames=7, seed=5, progress=False)


def make_mapper(seq, config=None, params=None):
    """A mapper of ``seq``'s KEYFRAMES at their true poses: Gaussians inserted from the true
    depth, or ``params`` (a map's arrays, or a Mapper whose map and background it copies)."""
    from problems import Problem

    from mcgs_warp.mapping.mapper import Mapper

    P = Problem(seq, KEYFRAMES, cross_view=False)
    m = Mapper(P.buf, config=config)
    if isinstance(params, Mapper):
        m.background.assign(params.background.numpy())
        params = params.map.to_numpy()
    if params is None:
        for k, f in enumerate(KEYFRAMES):
            m.add_keyframe(k, seq[f].depths)
    else:
        m.map.set_numpy(params)
        for k, f in enumerate(KEYFRAMES):
            m.buf.targets[k] = seq[f].depths
    return m


@pytest.fixture(scope="session")
def fitted(mapping_seq):
    """A map fitted for 150 iterations on 4 keyframes x 3 cameras (and its PSNRs): densified
    at 100, then optimized on (a map right after a densify step is not what a run outputs)."""
    m = make_mapper(mapping_seq)
    m.optimize(150)
    return m
