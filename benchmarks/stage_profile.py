"""Where a run's time goes: seconds per stage and the share of them inside Warp kernels and OpenCV.

    python benchmarks/stage_profile.py [--data ../shared/data/kitti_stereo_excerpt] [--out out/profile]
        [--every 1] [--config C.yaml] [--cprofile out/profile/run.prof] [--device cuda:0]

Runs ``mcgs-slam run`` in this process (default configuration unless ``--config``) with each
stage's entry point wrapped: the time of a call is charged to the innermost stage running
(so "keyframe step" excludes the MCBA solves it calls and "offline" global BA, the
photo-depth pass and refinement; refinement, the photo-depth pass and the outputs keep what
they call). Warp's CPU launches are synchronous, so the time the main
thread spends in ``wp.launch`` plus the time it waits for the row bands' worker threads
(:mod:`kernels.launch`) is the wall time inside kernels; OpenCV's functions and the methods of
the objects it makes (SIFT, DIS flow, matchers) are timed alike; the rest is Python, NumPy and
copies: what a GPU could not shorten. The correspondences run DIS and their refinement
kernels per edge in worker threads on the CPU: the main thread's wait for them is its own column.
Prints one row per stage: calls, seconds, share of the run, seconds inside kernels and their
share of the stage, seconds inside OpenCV, waiting for thread pools, the seconds outside all
three, and the cores it kept busy (process CPU seconds of
every thread over wall seconds: 2.0 on two cores is both busy throughout; what a stage
leaves idle, another running beside it could use). Without the KITTI excerpt (its licence keeps it out of
the repository) it runs the built-in synthetic demo sequence instead. ``--cprofile`` also
writes a cProfile dump (``python -m pstats``) of the whole run.
"""

from __future__ import annotations

import argparse
import functools
import sys
import threading
import time
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_stereo_excerpt"

#: (module, owner, method, stage): the entry points charged to each stage
STAGES = [
    ("mcgs_warp.frontend.keypoint_odometry", "KeypointOdometry", "track", "odometry"),
    ("mcgs_warp.frontend.keyframes", "KeyframeSelector", "is_keyframe", "keyframe test"),
    ("mcgs_warp.system.tracker", "Tracker", "add_keyframe", "keyframe step"),
    ("mcgs_warp.ba.mcba", "MCBA", "solve", "MCBA solve"),
    ("mcgs_warp.mapping.mapper", "Mapper", "follow", "map follows"),
    ("mcgs_warp.mapping.mapper", "Mapper", "add_keyframe", "map insert"),
    ("mcgs_warp.mapping.mapper", "Mapper", "optimize", "mapping"),
    ("mcgs_warp.system.slam", None, "save_checkpoint", "checkpoint"),
    ("mcgs_warp.system.slam", "SLAM", "refine", "offline"),
    ("mcgs_warp.system.backend", "Backend", "run", "global BA"),
    ("mcgs_warp.system.slam", None, "photo_consistent_targets", "photo depth"),
    ("mcgs_warp.system.slam", None, "joint_refinement", "refinement"),
    ("mcgs_warp.system.run", None, "write_outputs", "outputs"),
]

#: stages charged with everything they call (refinement's mapping iterations are refinement)
WHOLE = {"refinement", "photo depth", "outputs"}


class StageClock:
    """Wall time per stage (innermost stage charged) and main-thread time inside Warp kernels."""

    def __init__(self):
        self.stack: list = []  # [stage, start, time of nested stages, CPU start, CPU of nested stages]
        self.seconds: dict = {}
        self.cpu: dict = {}  # process CPU seconds (every thread: row bands, OpenCV's) per stage
        self.kernel: dict = {}  # main-thread seconds inside Warp kernels per stage
        self.cv: dict = {}  # ... inside OpenCV
        self.pool: dict = {}  # ... waiting for thread pools (the correspondences' DIS and refinement kernels, per edge)
        self.calls: dict = {}
        self.main = threading.main_thread()
        self.in_native = False

    def stage(self, name, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if self.stack and self.stack[-1][0] in WHOLE:
                return fn(*args, **kwargs)
            self.stack.append([name, time.perf_counter(), 0.0, time.process_time(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                _, t0, nested, c0, cpu_nested = self.stack.pop()
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
                self.seconds[name] = self.seconds.get(name, 0.0) + dt - nested
                self.cpu[name] = self.cpu.get(name, 0.0) + dc - cpu_nested
                self.calls[name] = self.calls.get(name, 0) + 1
                if self.stack:
                    self.stack[-1][2] += dt
                    self.stack[-1][4] += dc
        return timed

    def native_time(self, fn, bucket: dict):
        """``fn`` with the main thread's wall time inside it charged to the running stage in
        ``bucket`` (Warp's kernels, OpenCV): time spent outside Python, once (not nested)."""

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if threading.current_thread() is not self.main or self.in_native:
                return fn(*args, **kwargs)
            self.in_native = True
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.in_native = False
                name = self.stack[-1][0] if self.stack else "other"
                bucket[name] = bucket.get(name, 0.0) + time.perf_counter() - t0
        return timed

    def opencv(self, cv2) -> None:
        """Time every OpenCV function, and the methods of the objects its factories make
        (SIFT, DIS flow, matchers), as :meth:`native_time` in ``self.cv``."""
        clock = self

        class Timed:
            def __init__(self, obj):
                self._obj = obj

            def __getattr__(self, name):
                a = getattr(self._obj, name)
                return clock.native_time(a, clock.cv) if callable(a) else a

        def factory(fn):
            @functools.wraps(fn)
            def make(*args, **kwargs):
                return Timed(fn(*args, **kwargs))
            return make

        for name in dir(cv2):
            v = getattr(cv2, name)
            if name.endswith("_create") or name == "BFMatcher":
                setattr(cv2, name, factory(v))
            elif type(v).__name__ == "builtin_function_or_method" and not name.startswith("_"):
                setattr(cv2, name, self.native_time(v, self.cv))

    def install(self) -> None:
        import importlib

        import warp as wp

        from mcgs_warp.kernels import launch

        import cv2

        wp.launch = self.native_time(wp.launch, self.kernel)
        launch.wait = self.native_time(launch.wait, self.kernel)  # the row bands' worker threads
        self.opencv(cv2)
        from concurrent.futures import ThreadPoolExecutor

        pool_map = ThreadPoolExecutor.map

        def eager_map(pool, fn, *iterables, **kwargs):  # waited for here, where it is timed
            return iter(list(pool_map(pool, fn, *iterables, **kwargs)))

        ThreadPoolExecutor.map = self.native_time(eager_map, self.pool)
        for module, owner, method, name in STAGES:
            mod = importlib.import_module(module)
            target = getattr(mod, owner) if owner else mod
            setattr(target, method, self.stage(name, getattr(target, method)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT)
    ap.add_argument("--out", type=Path, default=Path("out/profile"))
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--cprofile", type=Path, default=None)
    ap.add_argument("--device", default=None, help="Warp device, e.g. cuda:0 (default: Warp's default)")
    args = ap.parse_args()

    import warp as wp

    from mcgs_warp.cli import init_warp

    wp.config.log_level = wp.LOG_WARNING  # as the command line: no banner, no line per kernel module loaded
    init_warp(args.device)
    clock = StageClock()
    clock.install()
    from mcgs_warp.system.run import run_sequence

    data = args.data
    if not data.is_dir():
        from mcgs_warp.data.synthetic import generate
        from mcgs_warp.system.config import packaged_config

        data = args.out / "demo_data"
        print(f"no KITTI data at {args.data}: profiling the demo's synthetic sequence ({data})")
        generate(data, n_cameras=3, n_frames=40, seed=0, depth="exact")
        args.config = args.config or packaged_config("synthetic.yaml")
    clock.kernel.clear()  # the demo sequence's rendering is no part of the run
    clock.cv.clear()
    clock.pool.clear()
    t0, c0 = time.perf_counter(), time.process_time()
    if args.cprofile is not None:
        import cProfile

        args.cprofile.parent.mkdir(parents=True, exist_ok=True)
        prof = cProfile.Profile()
        prof.enable()
    run_sequence(data, args.out / "run", config=args.config, every=args.every, progress=False, device=args.device)
    if args.cprofile is not None:
        prof.disable()
        prof.dump_stats(str(args.cprofile))
    total, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    rest = total - sum(clock.seconds.values())
    clock.cpu["other (loop, loading)"] = total_cpu - sum(clock.cpu.values())
    rows = sorted(clock.seconds.items(), key=lambda kv: -kv[1]) + [("other (loop, loading)", rest)]
    print(f"\n{data} (--every {args.every}): {total:.1f} s\n")
    print(f"| {'stage':<22} | {'calls':>5} | {'seconds':>8} | {'of run':>6} | {'in kernels':>10} | {'share':>5} | {'in OpenCV':>9} | {'in pools':>8} | {'outside':>7} | {'cores':>5} |")
    print(f"|{'-' * 24}|{'-' * 7}|{'-' * 10}|{'-' * 8}|{'-' * 12}|{'-' * 7}|{'-' * 11}|{'-' * 10}|{'-' * 9}|{'-' * 7}|")
    for name, sec in rows:
        key = name if name in clock.seconds else "other"
        kern, cv, pool = clock.kernel.get(key, 0.0), clock.cv.get(key, 0.0), clock.pool.get(key, 0.0)
        cores = clock.cpu.get(name, 0.0) / max(sec, 1e-9)
        print(f"| {name:<22} | {clock.calls.get(name, ''):>5} | {sec:8.1f} | {100 * sec / total:5.1f}% | {kern:10.1f} | {100 * kern / max(sec, 1e-9):4.0f}% | {cv:9.1f} | {pool:8.1f} | {sec - kern - cv - pool:7.1f} | {cores:5.2f} |")
    kern_all, cv_all, pool_all = sum(clock.kernel.values()), sum(clock.cv.values()), sum(clock.pool.values())
    print(f"| {'total':<22} | {'':>5} | {total:8.1f} | 100.0% | {kern_all:10.1f} | {100 * kern_all / total:4.0f}% | {cv_all:9.1f} | {pool_all:8.1f} | {total - kern_all - cv_all - pool_all:7.1f} | {total_cpu / total:5.2f} |")
    print("\nin pools: the main thread waiting for worker threads (DIS flow and the refinement kernels per edge, on the CPU);")
    print("outside: the main thread's seconds in Python, NumPy and copies, which a faster Warp device does not shorten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
