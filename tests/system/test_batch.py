"""``mcgs-slam batch``: many sequences on a local Ray instance, a broken one reported while the
others finish, an interrupted batch resumed without recomputing what finished, the summary
matching each run's metrics.json, Waymo and nuScenes folders as one run per segment or scene,
and the hints where Ray or Ray Client is missing."""

import contextlib
import csv
import io
import json
import os
import shutil
import sys
from pathlib import Path

import pytest

from mcgs_warp.cli import main
from mcgs_warp.data.synthetic import generate
from mcgs_warp.errors import InputError
from mcgs_warp.system.batch import BATCH_JSON, RunOptions, connect, plan_runs, resolve_inputs, run_key, run_one, sequence_names

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from test_nuscenes import make_nuscenes  # noqa: E402
from waymo_fixture import SEGMENT, make_waymo  # noqa: E402

pytestmark = pytest.mark.slow  # runs the whole system: `pytest -m "not slow"` leaves it out

# a run of a 6-frame, 2-camera sequence in a few seconds (as tests/system/test_system.py's fast_config)
FAST_YAML = """\
tracking:
  mcba_iterations: 2
mapping:
  iterations_per_keyframe: 3
refinement:
  global_ba_iterations: 1
  iterations: 4
output:
  renders: 1
"""
NAMES = ("s1", "s2", "s3")
#: summary.csv column -> metrics.json key
SAME_AS_METRICS = {"frames": "n_frames", "keyframes": "n_keyframes", "ate_se3_m": "ate_se3_rmse_m", "ate_sim3_m": "ate_rmse_m",
                   "sim3_scale": "sim3_scale", "psnr_db": "psnr_db", "tracking_failures": "tracking_failures"}


def batch(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def read_csv(path) -> dict:
    with open(path, newline="") as f:
        return {row["sequence"]: row for row in csv.DictReader(f)}


def mtimes(folder) -> dict:
    return {p.relative_to(folder): p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    seqs = root / "sequences"
    for i, name in enumerate(NAMES):
        generate(seqs / name, n_cameras=2, n_frames=6, seed=i + 1, progress=False)
    broken = seqs / "broken"  # looks like a sequence, but its rig.yaml does not parse
    broken.mkdir()
    shutil.copy(seqs / "s1" / "timestamps.txt", broken / "timestamps.txt")
    (broken / "rig.yaml").write_text("cameras: [ {oops\n")
    (seqs / "notes").mkdir()  # not a sequence: left out of the folder's sequences
    config = root / "fast.yaml"
    config.write_text(FAST_YAML)
    return root, seqs, config


@pytest.fixture(scope="module")
def first(data):
    """A batch over the folder of sequences (three good, one broken), one CPU per run."""
    pytest.importorskip("ray")
    root, seqs, config = data
    out = root / "out"
    rc, stdout, err = batch(["batch", str(seqs), "--out", str(out), "--config", str(config), "--cpus-per-run", "1"])
    return out, rc, stdout, err


def test_batch_runs_every_sequence_and_reports_the_broken_one(data, first):
    root, seqs, config = data
    out, rc, stdout, err = first
    assert rc == 1, (stdout, err)  # one sequence failed
    lines = [ln for ln in stdout.splitlines() if ln.startswith("[")]
    assert len(lines) == 4 and {ln.split("]")[0] for ln in lines} == {f"[{k}/4" for k in range(1, 5)}, stdout
    status = {ln.split()[1]: ln.split()[2] for ln in lines}
    assert status == {"s1": "ok", "s2": "ok", "s3": "ok", "broken": "failed"}, stdout
    broken_line = next(ln for ln in lines if " broken " in ln)
    assert "rig.yaml" in broken_line and "YAML" in broken_line, broken_line  # the run's last error line
    assert all(" ATE " in ln and " PSNR " in ln and ln.endswith(" s") for ln in lines if " ok " in ln), stdout
    assert "1 failed (broken)" in stdout

    fields = RunOptions.of(config=str(config)).key_fields()
    rows = read_csv(out / "summary.csv")
    assert set(rows) == {*NAMES, "broken"}
    for name in NAMES:
        run = out / name
        for f in ("trajectory.txt", "metrics.json", "config.yaml", "map.ply", "plots/trajectory.png"):
            assert (run / f).is_file(), (name, f)
        record = json.loads((run / BATCH_JSON).read_text())
        assert record["key"] == run_key(seqs / name, fields) and record["peak_rss_mb"] > 50
        metrics = json.loads((run / "metrics.json").read_text())
        row = rows[name]
        assert row["status"] == "ok" and row["error"] == ""
        for col, key in SAME_AS_METRICS.items():
            assert float(row[col]) == pytest.approx(metrics[key], rel=1e-12, abs=0), (name, col)
        assert float(row["seconds"]) == pytest.approx(record["seconds"]) and float(row["peak_rss_mb"]) == pytest.approx(record["peak_rss_mb"])
        assert metrics["n_frames"] == 6 and metrics["ate_se3_rmse_m"] < 0.01
    assert rows["broken"]["status"] == "failed" and "rig.yaml" in rows["broken"]["error"] and rows["broken"]["psnr_db"] == ""
    assert not (out / "broken" / BATCH_JSON).exists()
    assert "rig.yaml" in (out / "logs" / "broken.log").read_text()
    md = (out / "summary.md").read_text()
    assert "| **mean** |" in md and "| **worst** |" in md and "## Failed" in md and all(f"\n| {n} | ok |" in md for n in NAMES)
    assert (out / "summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*.tmp")) and not (out / "notes").exists()


def test_batch_output_is_what_run_writes(data, first):
    """A sequence's batch folder holds what `mcgs-slam run` with the same options writes, and batch.json."""
    root, seqs, config = data
    out = first[0]
    direct = root / "direct"
    rc, _, err = batch(["--device", "cpu", "run", "--data", str(seqs / "s1"), "--out", str(direct), "--config", str(config)])
    assert rc == 0, err
    files = {str(p) for p in mtimes(direct)}
    assert {str(p) for p in mtimes(out / "s1")} == files | {BATCH_JSON}
    assert (direct / "config.yaml").read_text() == (out / "s1" / "config.yaml").read_text()
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (direct, out / "s1"))
    assert a["n_keyframes"] == b["n_keyframes"] and a["n_frames"] == b["n_frames"]


def test_interrupted_batch_resumes_without_recomputing(data, first, tmp_path):
    """s1 finished (skipped, its files untouched), s2 finished under another configuration
    (run again), s3 was interrupted before its run finished (run again); a list file names them."""
    pytest.importorskip("ray")
    root, seqs, config = data
    out = tmp_path / "out"
    for name in NAMES:
        shutil.copytree(first[0] / name, out / name)  # copy2: modification times kept
    record = json.loads((out / "s2" / BATCH_JSON).read_text())
    (out / "s2" / BATCH_JSON).write_text(json.dumps({**record, "key": "0" * 64}))
    (out / "s3" / BATCH_JSON).unlink()
    (out / "s3" / "metrics.json").unlink()
    before = mtimes(out / "s1")
    listing = tmp_path / "sequences.txt"
    listing.write_text(f"# the three good ones\n{seqs / 's1'}\n\n{os.path.relpath(seqs / 's2', tmp_path)}  # relative to this file\n{seqs / 's3'}\n")

    rc, stdout, err = batch(["batch", str(listing), "--out", str(out), "--config", str(config)])
    assert rc == 0, (stdout, err)
    status = {ln.split()[1]: ln.split()[2] for ln in stdout.splitlines() if ln.startswith("[")}
    assert status == {"s1": "skipped", "s2": "ok", "s3": "ok"}, stdout
    assert mtimes(out / "s1") == before
    fields = RunOptions.of(config=str(config)).key_fields()
    for name in ("s2", "s3"):
        assert json.loads((out / name / BATCH_JSON).read_text())["key"] == run_key(seqs / name, fields)
        assert (out / name / "metrics.json").is_file()
    rows = read_csv(out / "summary.csv")
    assert [rows[n]["status"] for n in NAMES] == ["skipped", "ok", "ok"]
    metrics, done = (json.loads((out / "s1" / f).read_text()) for f in ("metrics.json", BATCH_JSON))
    assert float(rows["s1"]["psnr_db"]) == metrics["psnr_db"] and float(rows["s1"]["seconds"]) == pytest.approx(done["seconds"])  # from the earlier run


def test_run_key_follows_the_effective_configuration(data, tmp_path):
    root, seqs, config = data
    same = tmp_path / "same.yaml"
    same.write_text(FAST_YAML)
    other = tmp_path / "other.yaml"
    other.write_text(FAST_YAML.replace("iterations: 4", "iterations: 5"))
    s1 = seqs / "s1"
    key = run_key(s1, RunOptions.of(config=str(config)).key_fields())
    assert run_key(s1, RunOptions.of(config=str(same), device="cuda:0", resume=True).key_fields()) == key  # where and how it runs: same result
    assert run_key(s1, RunOptions.of(config=str(other)).key_fields()) != key
    assert run_key(s1, RunOptions.of(config=str(config), every=2).key_fields()) != key
    assert run_key(s1, RunOptions.of(config=str(config), cameras="0").key_fields()) != key
    assert run_key(seqs / "s2", RunOptions.of(config=str(config)).key_fields()) != key
    # an option and the configuration key it overrides are one setting
    with_depth = tmp_path / "depth.yaml"
    with_depth.write_text(FAST_YAML.replace("tracking:\n", "tracking:\n  depth: sensor\n"))
    assert run_key(s1, RunOptions.of(config=str(with_depth)).key_fields()) == run_key(s1, RunOptions.of(config=str(config), depth="sensor").key_fields())


def test_inputs_sequences_lists_and_folders(data, tmp_path):
    root, seqs, config = data
    found = resolve_inputs([seqs], exclude=seqs / "s3")
    assert [p.name for p in found] == ["broken", "s1", "s2"]  # sorted, "notes" and the output folder left out
    assert [p.name for p in resolve_inputs([seqs / "s2", seqs])] == ["s2", "broken", "s1", "s3"]  # each once, in order
    listing = tmp_path / "list.txt"
    listing.write_text(f"{seqs / 's1'}\n# {seqs / 's2'}\n")
    assert resolve_inputs([listing]) == [seqs / "s1"]
    listing.write_text(f"{os.path.relpath(seqs / 's1', tmp_path)}\nnowhere  # a typo\n")
    with pytest.raises(InputError, match="line 2.*nowhere"):
        resolve_inputs([listing])
    with pytest.raises(InputError, match="no such"):
        resolve_inputs([tmp_path / "missing"])
    with pytest.raises(InputError, match="folder of sequences"):
        resolve_inputs([seqs / "notes"])
    assert sequence_names([root / "a" / "00", root / "b" / "00", root / "c" / "seq"]) == ["a_00", "b_00", "seq"]


def test_batch_passes_runs_the_options_that_differ_from_runs_defaults(data, tmp_path, monkeypatch):
    import mcgs_warp.system.batch as batch_module

    root, seqs, config = data
    seen = {}
    monkeypatch.setattr(batch_module, "run_batch", lambda inputs, out, options, **kw: seen.update(inputs=inputs, options=options, **kw) or [])
    rc, stdout, _ = batch(["--device", "cpu", "batch", str(seqs / "s1"), "--data", str(seqs / "s2"), "--out", str(tmp_path / "o"), "--config", str(config),
                           "--every", "2", "--no-jdsa", "--resume", "--gpus-per-run", "0.5", "--address", "auto"])
    assert rc == 0 and seen["inputs"] == [str(seqs / "s1"), str(seqs / "s2")], stdout
    assert seen["options"].argv("SEQ", "OUT") == ["--device", "cpu", "run", "--data", os.path.abspath("SEQ"), "--out", os.path.abspath("OUT"),
                                                  "--config", str(config), "--no-jdsa", "--every", "2", "--resume"]
    assert seen["gpus_per_run"] == 0.5 and seen["cpus_per_run"] == 1.0 and seen["address"] == "auto"


def test_batch_without_ray_says_how_to_install(data, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    root, seqs, config = data
    rc, stdout, err = batch(["batch", str(seqs), "--out", str(tmp_path / "out")])
    assert rc == 2 and 'pip install "mcgs_warp[cluster]"' in err, err
    assert not (tmp_path / "out").exists()


def test_waymo_and_nuscenes_folders_are_one_run_per_segment(data, tmp_path):
    """A Waymo v2 folder (given, in a folder of sequences or listed) is one run per segment, a
    nuScenes root one per scene: each `run --segment NAME` into OUT/<segment>, keyed by it."""
    pytest.importorskip("pyarrow")
    root, seqs, config = data
    waymo = make_waymo(tmp_path / "waymo" / "training", n=2)
    make_waymo(waymo, segment="seg_b", n=2)
    nus = make_nuscenes(tmp_path / "nuscenes", scenes=("scene-0061", "scene-0103"), n=2, sweeps=False)
    out = tmp_path / "out"
    options = RunOptions.of(config=str(config), waymo_cameras="all")
    tasks = plan_runs([waymo, seqs / "s1", nus], out, options)
    names = [SEGMENT, "seg_b", "s1", "scene-0061", "scene-0103"]
    assert [t["name"] for t in tasks] == names
    fields = options.key_fields()
    for t, data_path in zip(tasks, [waymo, waymo, seqs / "s1", nus, nus]):
        seg = None if t["name"] == "s1" else t["name"]
        assert t["segment"] == seg and t["data"] == os.path.abspath(data_path) and t["out"] == os.path.abspath(out / t["name"])
        assert t["argv"] == ["run", "--data", os.path.abspath(data_path), "--out", os.path.abspath(out / t["name"]), *(["--segment", seg] if seg else []),
                             "--config", os.path.abspath(config), "--waymo-cameras", "all"]
        assert t["key"] == run_key(data_path, fields, seg) and t["log"] == os.path.abspath(out / "logs" / f"{t['name']}.log")
    assert len({t["key"] for t in tasks}) == 5 and run_key(seqs / "s1", fields) == run_key(seqs / "s1", fields, None)  # a plain sequence's key is unchanged
    # a folder holding the Waymo folder, and a list file naming it, expand it the same way
    listing = tmp_path / "list.txt"
    listing.write_text("waymo/training\n")
    for given in (tmp_path / "waymo", listing):
        assert [(t["name"], t["segment"]) for t in plan_runs([given], out)] == [(SEGMENT, SEGMENT), ("seg_b", "seg_b")]
    # the batch's own --segment runs that one alone (once on each command line); one a folder lacks is an error
    (t,) = plan_runs([waymo], out, RunOptions.of(segment="seg_b"))
    assert t["name"] == "seg_b" and t["argv"].count("--segment") == 1 and t["argv"][-2:] == ["--segment", "seg_b"]
    with pytest.raises(InputError, match=r"training: --segment: no segment or scene 'nope'; found: 10023947602400723454_1120_000_1140_000, seg_b"):
        plan_runs([waymo], out, RunOptions.of(segment="nope"))
    # the same segment in two folders: named by folder and segment
    shutil.copytree(waymo, tmp_path / "waymo" / "validation")
    assert [t["name"] for t in plan_runs([waymo, tmp_path / "waymo" / "validation"], out)] == [
        f"training_{SEGMENT}", "training_seg_b", f"validation_{SEGMENT}", "validation_seg_b"]
    # a Waymo folder without segments says so before anything runs
    for p in (waymo / "camera_image").iterdir():
        p.unlink()
    with pytest.raises(InputError, match="camera_image: a Waymo Open Dataset v2 folder without segments"):
        plan_runs([waymo], out)


def test_batch_runs_each_waymo_segment(data, tmp_path):
    """A real batch of a two-segment Waymo folder: each segment's own run (its own frame count),
    named by segment in the progress lines and the summary; run again, both are skipped."""
    pytest.importorskip("pyarrow")
    pytest.importorskip("ray")
    root, seqs, config = data
    waymo = make_waymo(tmp_path / "training", n=6)
    make_waymo(waymo, segment="seg_b", n=5)
    out = tmp_path / "out"
    rc, stdout, err = batch(["batch", str(waymo), "--out", str(out), "--config", str(config)])
    assert rc == 0, (stdout, err)
    status = {ln.split()[1]: ln.split()[2] for ln in stdout.splitlines() if ln.startswith("[")}
    assert status == {SEGMENT: "ok", "seg_b": "ok"}, stdout
    rows = read_csv(out / "summary.csv")
    assert list(rows) == [SEGMENT, "seg_b"] and [rows[n]["frames"] for n in rows] == ["6", "5"]
    for name, n in ((SEGMENT, 6), ("seg_b", 5)):
        assert json.loads((out / name / "metrics.json").read_text())["n_frames"] == n
        record = json.loads((out / name / BATCH_JSON).read_text())
        assert record["segment"] == name and record["command"][record["command"].index("--segment") + 1] == name and (out / "logs" / f"{name}.log").is_file()
    tasks = plan_runs([waymo], out, RunOptions.of(config=str(config)))
    assert [run_one(t)["status"] for t in tasks] == ["skipped", "skipped"]  # resume: the keys match what the batch recorded


def test_ray_client_address_without_ray_client_says_what_to_install(monkeypatch):
    """`--address ray://...` with Ray but not Ray Client (no grpcio): what Ray raises becomes the install hint."""
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")

    class MinimalRay:  # ray.init as Ray 2.x raises it (ray/client_builder.py) without the client extra
        @staticmethod
        def is_initialized():
            return False

        @staticmethod
        def init(address, **kw):
            raise ValueError("Ray Client requires pip package `ray[client]`. If you installed the minimal Ray (e.g. `pip install ray`), "
                             "please reinstall by executing `pip install ray[client]`.")

    with pytest.raises(InputError, match=r'--address: ray://head:10001: a ray:// address needs Ray Client: pip install "ray\[client\]>=2.9"'):
        connect(MinimalRay, "ray://head:10001")
