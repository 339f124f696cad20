"""Fuzzing the readers and loaders: random and malformed content raises InputError or
parses, never anything else (no KeyError, TypeError, IndexError, ... escaping)."""

import string

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mcgs_warp.data.sequence import read_timestamps
from mcgs_warp.data.trajectory import read_tum
from mcgs_warp.errors import InputError
from mcgs_warp.rig import load_rig, rig_from_dict
from mcgs_warp.system.config import load_run_config

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10, 10**6), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=6), st.dictionaries(st.text(max_size=10), inner, max_size=6)), max_leaves=30)
camera_keys = st.sampled_from(["name", "model", "resolution", "intrinsics", "distortion", "T_b_c", "time_offset", "extra"])
cameras = st.dictionaries(camera_keys, st.one_of(values, st.sampled_from(["pinhole", "fisheye", "equirectangular"]), st.just([320, 240]), st.just([1.0, 1.0, 0.5, 0.5])), max_size=7)


def only_input_errors(fn, *args):
    try:
        fn(*args)
    except InputError:
        pass


@SETTINGS
@given(st.one_of(values, st.fixed_dictionaries({"cameras": st.lists(cameras, max_size=4)})))
def test_rig_from_random_structures(data):
    only_input_errors(rig_from_dict, data, "fuzz.yaml")


@SETTINGS
@given(st.text(alphabet=string.printable, max_size=300))
def test_yaml_files_with_random_text(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("fuzz") / "rig.yaml"
    path.write_text(text)
    only_input_errors(load_rig, path)
    only_input_errors(load_run_config, path)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["seed", "tracking", "mapping", "refinement", "output", "bogus"]), st.one_of(values, st.dictionaries(st.sampled_from(["window", "stride", "jdsa", "lr_means", "renders", "stereo", "graph", "x"]), scalars, max_size=4)), max_size=5))
def test_run_config_with_random_values(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("fuzz") / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    only_input_errors(load_run_config, path)


line = st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(alphabet="0123456789.-e+naifx#, ", max_size=6)), max_size=10).map(" ".join)


@SETTINGS
@given(st.lists(line, max_size=8))
def test_trajectory_and_timestamp_files(tmp_path_factory, lines):
    d = tmp_path_factory.mktemp("fuzz")
    (d / "t.txt").write_text("\n".join(lines))
    only_input_errors(read_tum, d / "t.txt")
    only_input_errors(read_timestamps, d / "t.txt")


@SETTINGS
@given(st.binary(max_size=200))
def test_binary_garbage_in_text_files(tmp_path_factory, blob):
    d = tmp_path_factory.mktemp("fuzz")
    (d / "t.txt").write_bytes(blob)
    only_input_errors(read_tum, d / "t.txt")
    only_input_errors(load_rig, d / "t.txt")


def test_valid_files_still_parse(tmp_path):
    (tmp_path / "t.txt").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    assert len(read_tum(tmp_path / "t.txt")) == 2
    assert np.allclose(read_timestamps(tmp_path / "t.txt"), [0, 1])


def test_huge_quaternions_do_not_overflow(tmp_path):
    (tmp_path / "t.txt").write_text("0 0 0 0 1e308 0 0 1e308\n")
    T = read_tum(tmp_path / "t.txt").poses[0]
    assert np.isfinite(T).all() and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))


def test_a_number_as_a_yaml_key_is_named_in_the_error(tmp_path):
    """Hypothesis found it: ``1: x`` beside ``cameras`` made the error message itself fail
    (a non-string field joined into it)."""
    path = tmp_path / "rig.yaml"
    path.write_text("cameras: []\n1: x\n")
    with pytest.raises(InputError, match=r"rig\.yaml: 1: unexpected field"):
        load_rig(path)
