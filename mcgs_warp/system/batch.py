"""Many sequences on Ray (the CLI's ``batch``): one Ray task per sequence, each running
``mcgs-slam run`` in a child process, so a crash or a memory blow-up ends that run alone and
its memory goes back to the system when it ends.

What a batch leaves in ``OUT``:

* ``OUT/<sequence>/``: exactly what ``mcgs-slam run --data SEQ --out OUT/<sequence>`` writes
  (the same options), plus ``batch.json``: the run's key (a hash of the effective
  configuration, the options, the input path and segment), its wall time and peak memory, written only
  after the run finished. A later batch skips a sequence whose ``batch.json`` has the same key
  and whose ``metrics.json`` is there; any other sequence runs again from the start.
* ``OUT/logs/<sequence>.log``: the run's console output (stdout and stderr).
* ``OUT/summary.csv`` (one row per sequence), ``OUT/summary.md`` (the same, then mean and worst
  rows and the failures' error lines) and ``OUT/summary.png`` (ATE and PSNR per sequence).

A Waymo Open Dataset v2 folder (``camera_image/`` + ``camera_calibration/``) or a nuScenes root
(``v1.0-*/``) is one run per segment or scene, each ``run --data ROOT --segment NAME`` into
``OUT/<segment>/`` (the batch's own ``--segment NAME``: that one alone); see :func:`plan_runs`.

Ray is an optional dependency (``pip install "mcgs_warp[cluster]"``), imported only here, and
only when a batch starts. On a cluster every node sees the inputs and ``OUT`` under the same
paths (a shared file system) and has this package installed.

``python -m mcgs_warp.system.batch_child ARGS`` is the child process: ``mcgs-slam ARGS`` that ends
when the Ray worker that started it ends (Linux), so an interrupted batch leaves no run behind.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from ..errors import InputError
from ..io import atomic_write

INSTALL_HINT = 'batch runs on Ray, which is not installed: pip install "mcgs_warp[cluster]" (or pip install "ray[client]>=2.9")'
BATCH_FORMAT = 1  #: raise it when the key's recipe changes: every earlier batch.json then mismatches
BATCH_JSON = "batch.json"
LOCAL_OBJECT_STORE_BYTES = 256 * 1024**2  # a local instance's object store: tasks exchange small dicts only
SUMMARY_FIGURE_HEIGHT = 700  # px of summary.png; its width grows with the number of sequences

#: summary columns: (column, metrics.json key, markdown header); a key of None is the batch's own measure
COLUMNS = (
    ("frames", "n_frames", "frames"),
    ("keyframes", "n_keyframes", "keyframes"),
    ("ate_se3_m", "ate_se3_rmse_m", "SE(3) ATE (m)"),
    ("ate_sim3_m", "ate_rmse_m", "Sim(3) ATE (m)"),
    ("sim3_scale", "sim3_scale", "scale"),
    ("psnr_db", "psnr_db", "PSNR (dB)"),
    ("tracking_failures", "tracking_failures", "tracking failures"),
    ("seconds", None, "seconds"),
    ("peak_rss_mb", None, "peak memory (MB)"),
)


class RayMissing(RuntimeError):
    """Ray is not installed; the message says how to install it."""


#: run options whose value is a file: absolute for the runs (they start elsewhere), and their contents are part of the key
PATH_OPTIONS = ("--config", "--rig", "--from-kalibr")
#: run options that set a key of the run configuration: the key holds them through the effective configuration
CONFIG_OPTIONS = ("--config", "--depth", "--correspondences", "--no-jdsa")
#: run options that change how a run proceeds, not its result
NOT_IN_KEY = ("--resume",)
#: the run option that picks a Waymo segment or nuScenes scene: set per run, a batch's own value only filters
SEGMENT = "--segment"


@dataclass(frozen=True)
class RunOptions:
    """The ``run`` options a batch passes to every sequence, as on its command line:
    ``options`` pairs ``(flag, value)`` (``True`` for a switch; ``None`` or ``False``: left out),
    e.g. ``(("--config", "fast.yaml"), ("--every", 2), ("--no-jdsa", True))``; ``device`` is the
    global ``--device``. :meth:`of` builds them from keyword arguments (``no_jdsa=True``). Paths
    may be relative to the current folder; the runs get them absolute."""

    options: tuple = ()
    device: str | None = None

    @classmethod
    def of(cls, device: str | None = None, **options) -> "RunOptions":
        """``RunOptions.of(config="fast.yaml", every=2)``: keyword ``name`` is ``--name`` (``_`` as ``-``)."""
        return cls(tuple((f"--{k.replace('_', '-')}", v) for k, v in options.items()), device)

    def get(self, flag: str, default=None):
        return next((v for f, v in self.options if f == flag and v is not None), default)

    def argv(self, data, out, segment: str | None = None) -> list[str]:
        """The command line ``mcgs-slam ARGV`` that runs ``data`` (its ``segment``, if not None) into ``out``."""
        picks = [] if segment is None else [SEGMENT, segment]
        return ([] if self.device is None else ["--device", self.device]) + ["run", "--data", _abs(data), "--out", _abs(out), *picks, *self.run_args()]

    def without(self, flag: str) -> "RunOptions":
        """These options less ``flag``."""
        return replace(self, options=tuple((f, v) for f, v in self.options if f != flag))

    def run_args(self) -> list[str]:
        """The options after ``run --data SEQ --out OUT``."""
        a = []
        for flag, value in self.options:
            if value is True:
                a.append(flag)
            elif value is not None and value is not False:
                values = value if isinstance(value, (list, tuple)) else [value]
                a += [flag, *(_abs(v) if flag in PATH_OPTIONS else str(v) for v in values)]
        return a

    def effective_config(self) -> dict:
        """The resolved run configuration with the options that override it applied (as
        :func:`~mcgs_warp.system.run.run_sequence` applies them); raises InputError for a bad file."""
        from .config import load_run_config

        cfg = load_run_config(self.get("--config"))
        if self.get("--no-jdsa", False):
            cfg.tracking.jdsa = False
        if self.get("--depth") is not None:
            cfg.tracking.depth = self.get("--depth")
        if self.get("--correspondences") is not None:
            cfg.tracking.correspondences = self.get("--correspondences")
        return cfg.to_dict()

    def key_fields(self) -> dict:
        """What, besides the input path, decides a run's result: the effective configuration,
        every other option (a file by its path and contents). Not ``device`` (where it runs)
        nor ``--resume`` (how it gets there)."""
        from .. import __version__

        other = {}
        for flag, value in self.options:
            if flag in CONFIG_OPTIONS or flag in NOT_IN_KEY or value is None or value is False:
                continue
            other[flag] = [_abs(value), _file_sha256(value)] if flag in PATH_OPTIONS else value
        return {"format": BATCH_FORMAT, "version": __version__, "config": self.effective_config(), "options": other}


def run_key(data, fields: dict, segment: str | None = None) -> str:
    """The key of running ``data`` (its ``segment``: a Waymo segment or nuScenes scene) with
    ``fields`` (:meth:`RunOptions.key_fields`): a SHA-256 hex digest."""
    picks = {} if segment is None else {"segment": segment}  # a plain sequence's key as before segments existed
    text = json.dumps({"input": _abs(data), **picks, **fields}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _abs(path) -> str | None:
    return None if path is None else os.path.abspath(os.fspath(path))


def _file_sha256(path) -> str | None:
    if path is None or not Path(path).is_file():
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ---------------------------------------------------------------------------------------------
# Inputs


def looks_like_sequence(path: Path) -> bool:
    """Whether ``path`` has the layout of a sequence :func:`~mcgs_warp.data.open_sequence`
    reads, without reading it: a ROS bag, a folder with ``timestamps.txt``, ``rig.yaml`` or
    ``rgb.txt``, or one a reader's ``is_<format>`` predicate that :mod:`mcgs_warp.data` exports
    accepts (EuRoC, KITTI, ...). A damaged sequence still counts, so that its run says what is wrong."""
    from .. import data
    from ..data.rosbag import bag_paths

    if bag_paths(path) is not None:
        return True
    if not path.is_dir():
        return False
    if any((path / n).is_file() for n in ("timestamps.txt", "rig.yaml", "rgb.txt")):
        return True
    return any(f(path) for name, f in vars(data).items() if name.startswith("is_") and callable(f))


def read_list(path: Path) -> list[Path]:
    """The sequences a text file lists, one a line; ``#`` starts a comment, blank lines are
    skipped, relative paths are relative to the file's folder."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, None, f"could not read the list of sequences ({e})") from None
    seqs = []
    for i, line in enumerate(lines, 1):
        entry = line.split("#", 1)[0].strip()
        if not entry:
            continue
        p = Path(entry).expanduser()
        p = p if p.is_absolute() else path.parent / p
        if not p.exists():
            raise InputError(path, f"line {i}", f"{entry}: no such sequence folder or bag")
        seqs.append(p)
    if not seqs:
        raise InputError(path, None, "lists no sequence (one folder or bag a line, # comments)")
    return seqs


def resolve_inputs(inputs, exclude=None) -> list[Path]:
    """The sequences ``inputs`` name, in order, each once: a sequence (folder or bag), a text
    file listing sequences (:func:`read_list`), or a folder of sequences (its subfolders and bags
    that look like sequences, sorted by name; ``exclude``, the batch's output folder, is not
    one of them)."""
    if not inputs:
        raise InputError(None, "DATA", "name at least one sequence, list file or folder of sequences")
    skip = _abs(exclude) if exclude is not None else None
    seqs: list[Path] = []
    for item in inputs:
        p = Path(item).expanduser()
        if not p.exists():
            raise InputError(p, None, "no such sequence, list file or folder of sequences")
        if looks_like_sequence(p):
            seqs.append(p)
        elif p.is_file():
            seqs += read_list(p)
        else:
            found = [c for c in sorted(p.iterdir()) if _abs(c) != skip and looks_like_sequence(c)]
            if not found:
                raise InputError(p, None, "neither a sequence nor a folder of sequences: no subfolder or bag in it has a layout mcgs-slam reads "
                                 "(rig.yaml + timestamps.txt, mav0/, calib.txt + image_0/, rgb.txt, a ROS bag, ...)")
            seqs += found
    unique = {}
    for s in seqs:
        unique.setdefault(_abs(s), s)
    return list(unique.values())


def dataset_segments(path: Path) -> list[str] | None:
    """The segments of a multi-segment dataset folder: a Waymo Open Dataset v2 folder's segment
    context names or a nuScenes root's scene names (sorted); None for any other sequence."""
    from ..data.nuscenes import is_nuscenes, nuscenes_scenes
    from ..data.waymo import is_waymo, waymo_segments

    if not path.is_dir():
        return None
    if is_waymo(path):
        found = waymo_segments(path)
        if not found:
            raise InputError(path / "camera_image", None, "a Waymo Open Dataset v2 folder without segments: expected <segment>.parquet files")
        return found
    if is_nuscenes(path):
        return nuscenes_scenes(path)
    return None


def expand_segments(seqs: list[Path], segment: str | None = None) -> list[tuple[Path, str | None]]:
    """``(sequence, segment)`` per run: a Waymo or nuScenes folder (:func:`dataset_segments`) once
    per segment or scene, or only ``segment`` of it when given; any other sequence once, with None."""
    runs = []
    for s in seqs:
        found = dataset_segments(s)
        if found is None:
            runs.append((s, None))
        elif segment is None:
            runs += [(s, g) for g in found]
        elif segment in found:
            runs.append((s, segment))
        else:
            shown = ", ".join(found[:12]) + (f", ... ({len(found)} in all)" if len(found) > 12 else "")
            raise InputError(s, SEGMENT, f"no segment or scene {segment!r}; found: {shown}")
    return runs


def run_names(runs: list[tuple[Path, str | None]]) -> list[str]:
    """A distinct output-folder name per run: a segment's own name (its folder's name and the
    segment where two folders hold the same one), else :func:`sequence_names`."""
    paths = list(dict.fromkeys(_abs(s) for s, _ in runs))
    folder = dict(zip(paths, sequence_names([Path(p) for p in paths])))
    names = [folder[_abs(s)] if g is None else g.replace(os.sep, "_") for s, g in runs]
    names = [f"{folder[_abs(s)]}_{n}" if g is not None and names.count(n) > 1 else n for (s, g), n in zip(runs, names)]
    seen: dict[str, int] = {}
    for i, n in enumerate(names):  # still the same (a sequence folder named like another's segment): numbered
        seen[n] = seen.get(n, 0) + 1
        names[i] = n if seen[n] == 1 else f"{n}_{seen[n]}"
    return names


def sequence_names(seqs: list[Path]) -> list[str]:
    """A distinct output-folder name per sequence: its folder or bag name (a bag without its
    suffix), where two collide with as many parent folders as make them distinct (``a_00``)."""
    parts = [Path(_abs(s)).parts for s in seqs]

    def name(i, depth):
        p = list(parts[i][-depth:])
        p[-1] = Path(p[-1]).stem if Path(_abs(seqs[i])).is_file() else p[-1]
        return "_".join(x.strip(os.sep) for x in p if x.strip(os.sep)) or "root"

    depth = [1] * len(seqs)
    while True:
        names = [name(i, d) for i, d in enumerate(depth)]
        clash = [i for i, n in enumerate(names) if names.count(n) > 1 and depth[i] < len(parts[i])]
        if not clash:
            return names
        for i in clash:
            depth[i] += 1


# ---------------------------------------------------------------------------------------------
# One sequence (a Ray task)


def finished(out: Path, key: str) -> dict | None:
    """``out``'s batch.json if the run there finished with ``key`` and left its metrics.json, else None."""
    try:
        record = json.loads((out / BATCH_JSON).read_text())
        if record.get("key") != key:
            return None
        record["metrics"] = json.loads((out / "metrics.json").read_text())
        return record
    except (OSError, ValueError, AttributeError):
        return None


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def _peak_mb(usage) -> float:
    # ru_maxrss: kilobytes on Linux, bytes on macOS
    return usage.ru_maxrss / (1024.0**2 if sys.platform == "darwin" else 1024.0)


def run_one(task: dict) -> dict:
    """Run one sequence (a Ray task's body): skip it if its outputs are complete for
    ``task["key"]``, else run ``python -m mcgs_warp.system.batch_child ARGV`` with the output in
    ``task["log"]``, and on success write ``batch.json``. Returns ``{name, status: ok | skipped
    | failed, metrics (dict or None), seconds (wall time of the run), peak_rss_mb, error}``."""
    out, log = Path(task["out"]), Path(task["log"])
    done = finished(out, task["key"])
    if done is not None:
        return {"name": task["name"], "status": "skipped", "metrics": done["metrics"], "seconds": done.get("seconds"), "peak_rss_mb": done.get("peak_rss_mb"), "error": None}
    with contextlib.suppress(FileNotFoundError):
        (out / BATCH_JSON).unlink()  # an earlier configuration's record: never valid for what this run leaves
    log.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")  # the log keeps stdout and stderr in order, so its last line is the error
    t0 = time.perf_counter()
    with open(log, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "mcgs_warp.system.batch_child", *task["argv"]], stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        try:
            _, status, usage = os.wait4(proc.pid, 0)  # this child's own peak memory (a reused worker's RUSAGE_CHILDREN holds every earlier run's)
        except BaseException:
            proc.kill()
            raise
        proc.returncode = rc = os.waitstatus_to_exitcode(status)
    seconds, peak = time.perf_counter() - t0, _peak_mb(usage)
    result = {"name": task["name"], "status": "failed", "metrics": None, "seconds": seconds, "peak_rss_mb": peak, "error": None}
    try:
        last = _last_line(log.read_text(errors="replace")[-20000:])
    except OSError:
        last = ""
    if rc != 0:
        if rc < 0:
            import signal

            try:
                sig = signal.Signals(-rc).name
            except ValueError:
                sig = f"signal {-rc}"
            why = f"killed by {sig}" + (" (out of memory?)" if sig == "SIGKILL" else "")
            result["error"] = f"{why}; last output: {last}" if last else why
        else:
            result["error"] = last or f"exit code {rc}"
        return result
    try:
        metrics = json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError) as e:
        result["error"] = f"the run finished without a readable metrics.json ({e})"
        return result
    record = {"key": task["key"], "input": task["data"], "segment": task.get("segment"), "command": ["mcgs-slam", *task["argv"]], "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
              "seconds": seconds, "peak_rss_mb": peak, "host": os.uname().nodename if hasattr(os, "uname") else None}
    with atomic_write(out / BATCH_JSON) as f:
        json.dump(record, f, indent=2)
    result.update(status="ok", metrics=metrics)
    return result


# ---------------------------------------------------------------------------------------------
# The batch


def import_ray():
    """The ``ray`` module, or :class:`RayMissing` with the install hint."""
    try:
        import ray
    except ImportError:
        raise RayMissing(INSTALL_HINT) from None
    return ray


def local_cpus() -> int:
    """This machine's cores (those this process may use, where the OS says)."""
    with contextlib.suppress(AttributeError, OSError):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def connect(ray, address: str | None) -> bool:
    """Join the Ray cluster at ``address`` (``auto``: the one ``ray start`` runs on this
    machine; ``ray://host:port``: Ray Client) or, for None, start a local instance sized to
    this machine, without dashboard and with the workers' output kept out of the console.
    Returns whether this call started Ray (and so should shut it down)."""
    import logging

    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage-stats notice or upload from a batch tool
    quiet = dict(include_dashboard=False, log_to_driver=False, configure_logging=True, logging_level=logging.ERROR)
    if address is None:
        ray.init(address="local", num_cpus=local_cpus(), object_store_memory=LOCAL_OBJECT_STORE_BYTES, **quiet)  # "local": a new instance even beside a `ray start` one
    else:
        if address.startswith("ray://"):
            quiet.pop("include_dashboard")  # the cluster's, not this client's
        try:
            ray.init(address=address, **quiet)
        except ConnectionError as e:
            raise InputError(None, "--address", f"no Ray cluster at {address} ({_last_line(str(e))}); start one with `ray start --head`, or leave --address out for a local one") from None
        except ValueError as e:
            if "ray[client]" not in str(e):
                raise
            raise InputError(None, "--address", f'{address}: a ray:// address needs Ray Client: pip install "ray[client]>=2.9" (or run the batch on a node of the cluster with --address auto)') from None
    return True


def check_resources(ray, cpus_per_run: float, gpus_per_run: float) -> None:
    """Refuse a run size no node of the cluster has (Ray would wait for it forever)."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive", True)]
    for name, need, flag in (("CPU", cpus_per_run, "--cpus-per-run"), ("GPU", gpus_per_run, "--gpus-per-run")):
        most = max((r.get(name, 0.0) for r in nodes), default=0.0)
        if need > most:
            raise InputError(None, flag, f"each run asks for {need:g} {name}s, but no node of the Ray cluster has more than {most:g}")


def progress_line(count: int, total: int, result: dict, width: int = 0) -> str:
    """``[3/12] seq  ok  ATE 0.12 m  PSNR 21.3 dB  84 s``: the ATE a user compares (SE(3) for a
    run with metric scale, else Sim(3)), as the run's trajectory plot shows it."""
    head = f"[{count}/{total}] {result['name']:<{width}}  {result['status']:<7}"
    if result["status"] == "failed":
        return f"{head}  {result['error']}"
    m = result["metrics"]
    ate = m.get("ate_se3_rmse_m") if m.get("metric_scale") else m.get("ate_rmse_m")
    text = f"{head}  ATE {ate:.3g} m" if ate is not None else f"{head}  ATE -"
    if m.get("psnr_db") is not None:
        text += f"  PSNR {m['psnr_db']:.1f} dB"
    if result.get("seconds") is not None:
        text += f"  {result['seconds']:.0f} s"
    return text


def plan_runs(inputs, out, options: RunOptions = RunOptions()) -> list[dict]:
    """The runs of a batch, in input order, one task dict each (:func:`run_one`): ``name``,
    ``data``, ``segment`` (None, or the Waymo segment / nuScenes scene), ``out``
    (``out/<name>``), ``log``, ``key`` and ``argv``. The sequences are :func:`resolve_inputs`'s,
    each Waymo or nuScenes folder among them expanded (:func:`expand_segments`; ``--segment``
    in ``options`` keeps that segment alone). Reads the configuration and lists the segments,
    runs nothing; raises InputError for bad inputs."""
    out = Path(out)
    seqs = resolve_inputs(inputs, exclude=out)
    runs = expand_segments(seqs, options.get(SEGMENT))
    options = options.without(SEGMENT)  # each run gets its own
    fields = options.key_fields()  # reads the configuration: a bad file stops the batch before anything runs
    return [{"name": n, "data": _abs(s), "segment": g, "out": _abs(out / n), "log": _abs(out / "logs" / f"{n}.log"), "key": run_key(s, fields, g),
             "argv": options.argv(s, out / n, g)} for n, (s, g) in zip(run_names(runs), runs)]


def run_batch(inputs, out, options: RunOptions = RunOptions(), address: str | None = None, cpus_per_run: float = 1.0, gpus_per_run: float = 0.0, echo=print) -> list[dict]:
    """Run every sequence ``inputs`` name (:func:`plan_runs`: one run per segment of a Waymo or
    nuScenes folder) with ``options`` into ``out/<name>``, one Ray task of ``cpus_per_run`` CPUs
    and ``gpus_per_run`` GPUs each (a run without a GPU runs on the CPU unless ``options.device``
    says otherwise), skipping those already finished for the same key; ``echo`` gets one
    progress line per run. Writes ``out/summary.{csv,md,png}`` and returns the results
    (:func:`run_one`) in input order."""
    ray = import_ray()
    out = Path(out)
    if cpus_per_run <= 0 or gpus_per_run < 0:
        raise InputError(None, "--cpus-per-run/--gpus-per-run", f"expected more than 0 CPUs and at least 0 GPUs per run, got {cpus_per_run:g} and {gpus_per_run:g}")
    if gpus_per_run == 0 and options.device is None:
        options = replace(options, device="cpu")
    tasks = plan_runs(inputs, out, options)
    names = [t["name"] for t in tasks]
    out.mkdir(parents=True, exist_ok=True)
    started = connect(ray, address)
    results: dict[str, dict] = {}
    try:
        check_resources(ray, cpus_per_run, gpus_per_run)
        remote = ray.remote(num_cpus=cpus_per_run, num_gpus=gpus_per_run)(run_one)
        pending = {remote.remote(t): t for t in tasks}
        width = max(map(len, names))
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                task = pending.pop(ref)
                try:
                    res = ray.get(ref)
                except ray.exceptions.RayError as e:  # the worker itself died (node lost, Ray's memory monitor)
                    res = {"name": task["name"], "status": "failed", "metrics": None, "seconds": None, "peak_rss_mb": None, "error": f"{type(e).__name__}: {_last_line(str(e))}"}
                results[task["name"]] = res
                echo(progress_line(len(results), len(tasks), res, width))
    finally:
        if started:
            ray.shutdown()
    ordered = [results[n] for n in names]
    write_summary(out, ordered, options)
    return ordered


# ---------------------------------------------------------------------------------------------
# The summary


def summary_rows(results: list[dict]) -> list[dict]:
    """One row per result: ``sequence``, ``status``, the :data:`COLUMNS` (None where unknown), ``error``."""
    rows = []
    for r in results:
        m = r["metrics"] or {}
        row = {"sequence": r["name"], "status": r["status"]}
        for col, key, _ in COLUMNS:
            row[col] = m.get(key) if key is not None else r.get(col)
        row["error"] = r.get("error")
        rows.append(row)
    return rows


def _mean_and_worst(rows: list[dict]) -> tuple[dict, dict]:
    """Per column over the runs with a value: the mean, and the worst (largest ATE, scale
    furthest from 1, lowest PSNR, most failures, time and memory; none for the counts)."""
    mean, worst = {}, {}
    for col, _, _ in COLUMNS:
        values = [float(r[col]) for r in rows if r[col] is not None and r["status"] != "failed"]
        mean[col] = sum(values) / len(values) if values else None
        if not values or col in ("frames", "keyframes"):
            worst[col] = None
        elif col == "sim3_scale":
            worst[col] = max(values, key=lambda s: abs(s - 1.0))
        elif col == "psnr_db":
            worst[col] = min(values)
        else:
            worst[col] = max(values)
    return mean, worst


def _cell(col: str, v) -> str:
    if v is None:
        return "-"
    if col in ("frames", "keyframes", "tracking_failures"):
        return f"{v:.1f}" if isinstance(v, float) and not float(v).is_integer() else f"{int(v)}"
    if col in ("ate_se3_m", "ate_sim3_m", "sim3_scale"):
        return f"{v:.4f}"
    return f"{v:.1f}" if col == "psnr_db" else f"{v:.0f}"


def summary_markdown(rows: list[dict], options: RunOptions | None = None) -> str:
    mean, worst = _mean_and_worst(rows)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "skipped", "failed")}
    lines = [f"# Batch summary: {len(rows)} sequences", "",
             f"{counts['ok']} run, {counts['skipped']} skipped (finished earlier with the same configuration), {counts['failed']} failed."]
    if options is not None:
        device = [] if options.device is None else ["--device", options.device]
        lines.append(f"Each sequence: `{' '.join(['mcgs-slam', *device, 'run', '--data', 'SEQ', '--out', 'OUT/SEQ', *options.run_args()])}`.")
    lines += ["", "| sequence | status | " + " | ".join(h for _, _, h in COLUMNS) + " |", "|---|---|" + "---:|" * len(COLUMNS)]
    for r in rows:
        lines.append(f"| {r['sequence']} | {r['status']} | " + " | ".join(_cell(c, r[c]) for c, _, _ in COLUMNS) + " |")
    for label, stats in (("mean", mean), ("worst", worst)):
        lines.append(f"| **{label}** | | " + " | ".join(_cell(c, stats[c]) for c, _, _ in COLUMNS) + " |")
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        lines += ["", "## Failed", ""] + [f"- **{r['sequence']}**: {r['error']} (log: logs/{r['sequence']}.log)" for r in failed]
    return "\n".join(lines) + "\n"


def summary_figure(rows: list[dict]):
    """Bar charts per sequence: SE(3) and Sim(3) ATE (top), PSNR (bottom); a failed run's name says so."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ..eval.plots import DPI

    n = len(rows)
    fig = Figure(figsize=(max(800, 60 * n + 200) / DPI, SUMMARY_FIGURE_HEIGHT / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax_ate, ax_psnr = fig.subplots(2, 1, sharex=True)
    x = np.arange(n)

    def values(col):
        return np.array([np.nan if r[col] is None else float(r[col]) for r in rows])

    ax_ate.bar(x - 0.2, values("ate_se3_m"), 0.4, label="SE(3)", color="tab:blue")
    ax_ate.bar(x + 0.2, values("ate_sim3_m"), 0.4, label="Sim(3)", color="tab:orange")
    ax_ate.set_ylabel("ATE RMSE (m)")
    ax_ate.legend(loc="upper right")
    ax_psnr.bar(x, values("psnr_db"), 0.6, color="tab:green")
    ax_psnr.set_ylabel("PSNR (dB)")
    labels = [r["sequence"] + (" (failed)" if r["status"] == "failed" else "") for r in rows]
    ax_psnr.set_xticks(x, labels, rotation=90 if n > 8 else 30, ha="center" if n > 8 else "right")
    for ax in (ax_ate, ax_psnr):
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"{n} sequences")
    return fig


def write_summary(out, results: list[dict], options: RunOptions | None = None) -> None:
    """``out/summary.csv`` (one row per sequence, full precision), ``summary.md`` and
    ``summary.png``, each written atomically."""
    from ..eval.plots import save_png

    out = Path(out)
    rows = summary_rows(results)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=["sequence", "status", *(c for c, _, _ in COLUMNS), "error"], lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if v is None or (isinstance(v, float) and math.isnan(v)) else v) for k, v in r.items()})
    with atomic_write(out / "summary.csv", newline="") as f:
        f.write(buf.getvalue())
    with atomic_write(out / "summary.md") as f:
        f.write(summary_markdown(rows, options))
    save_png(summary_figure(rows), out / "summary.png")

