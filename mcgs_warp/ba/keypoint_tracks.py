"""Keypoint tracks: which keypoints of which keyframe views are one 3D point, and the
:class:`~mcgs_warp.ba.keypoint_factors.KeypointProblem` of an MCBA window built from them.

Nodes are keypoints ``(keyframe, camera, index)``; verified matches join them (union-find):
stereo matches between the rig's cameras at one time, and the PnP inliers that anchored a
new keyframe against older ones. For a window, a track's source is its node in the earliest
keyframe of the window, its other nodes in the window are its observations, and its start
depth comes from the track's point as last solved (kept in world coordinates) or else from a
node's own depth (sensor, stereo) or the source keyframe's solved depth. After a solve the
point is read back from the source's new depth and pose.
"""

from __future__ import annotations

import numpy as np

from .keypoint_factors import KeypointProblem


class KeypointTracks:
    def __init__(self, weight: float = 1.0):
        self.weight = weight  # confidence of each keypoint observation (dense correspondences: DIS confidence in [0, 1])
        self.base: dict = {}  # (keyframe, camera) -> first node id of its keypoints
        self.count: dict = {}  # (keyframe, camera) -> number of its keypoints
        self.parent: list = []
        self.points: dict = {}  # root -> world point [3] as last solved
        self.nodes: list = []  # node id -> (keyframe, camera, index)

    def add_views(self, k: int, views) -> None:
        """Nodes for keyframe ``k``'s keypoints (``views`` [C] of ViewKeypoints), joined by
        their stereo matches."""
        for c, v in enumerate(views):
            self.base[(k, c)], self.count[(k, c)] = len(self.parent), len(v)
            self.parent.extend(range(len(self.parent), len(self.parent) + len(v)))
            self.nodes.extend((k, c, i) for i in range(len(v)))
        for c, v in enumerate(views):
            for d, (here, there) in v.partners.items():
                for a, b in zip(here, there):
                    self._union(self.base[(k, c)] + int(a), self.base[(k, d)] + int(b))

    def link(self, k: int, matches: np.ndarray) -> None:
        """Join keyframe ``k``'s keypoints to older ones: ``matches`` [M,5] ``(keyframe,
        camera there, index there, camera here, index here)``."""
        for j, d, b, c, a in np.asarray(matches, np.int64).tolist():
            if (j, d) in self.base and (k, c) in self.base:
                self._union(self.base[(j, d)] + b, self.base[(k, c)] + a)

    def world_points(self, k: int, c: int) -> np.ndarray:
        """[M,3] solved world points of keyframe ``k``'s camera-``c`` keypoints (NaN where their
        track has none yet)."""
        base, n = self.base[(k, c)], self.count[(k, c)]
        out = np.full((n, 3), np.nan)
        for i in range(n):
            p = self.points.get(self._find(base + i))
            if p is not None:
                out[i] = p
        return out

    def _find(self, x: int) -> int:
        p = self.parent
        while p[x] != x:
            p[x] = p[p[x]]
            x = p[x]
        return x

    def _union(self, a: int, b: int) -> None:
        ra, rb = self._find(a), self._find(b)
        if ra != rb:
            keep, drop = min(ra, rb), max(ra, rb)  # the older node stays the root
            self.parent[drop] = keep
            if drop in self.points and keep not in self.points:
                self.points[keep] = self.points[drop]
            self.points.pop(drop, None)

    def problem(self, window, views_of, poses: np.ndarray, T_b_c: np.ndarray, depth_at=None) -> tuple[KeypointProblem | None, list]:
        """The window's keypoint problem (slots in the order of ``window``) and the roots of
        its tracks. ``views_of(k)``: keyframe k's ViewKeypoints; ``poses`` [K,4,4] (or a dict) indexed by
        keyframe; ``T_b_c`` [C,4,4]; ``depth_at(k, c, uv)`` -> depth [M] (0: unknown)."""
        slot = {k: s for s, k in enumerate(window)}
        groups: dict = {}
        for k in window:
            for c in range(len(T_b_c)):
                base = self.base.get((k, c))
                if base is None:
                    continue
                for i in range(self.count[(k, c)]):
                    groups.setdefault(self._find(base + i), []).append((k, c, i))
        src_slot, src_cam, rays, disp, roots, held = [], [], [], [], [], []
        o_t, o_s, o_c, o_uv = [], [], [], []
        for root, nodes in groups.items():
            if len(nodes) < 2:
                continue
            nodes.sort()
            k0, c0, i0 = nodes[0]
            v0 = views_of(k0)[c0]
            ray = v0.rays[i0]
            T_w_c = poses[k0] @ T_b_c[c0]
            X_w = self.points.get(root)
            if X_w is None:
                X_w = self._initial_point(nodes, views_of, poses, T_b_c, depth_at)
            if X_w is None:
                continue
            X_c = T_w_c[:3, :3].T @ (X_w - T_w_c[:3, 3])
            proj = float(ray @ X_c)
            if proj <= 0:
                continue
            seen = {(k0, c0)}
            obs = []
            for k, c, i in nodes[1:]:
                if (k, c) in seen:  # two keypoints of one view in a track: a wrong match somewhere
                    continue
                seen.add((k, c))
                obs.append((slot[k], c, views_of(k)[c].uv[i]))
            if not obs:
                continue
            t = len(src_slot)
            src_slot.append(slot[k0])
            src_cam.append(c0)
            rays.append(ray)
            sensed = v0.sensed is not None and bool(v0.sensed[i0])
            held.append(sensed)
            # X_c projected on the ray: ray / d; a sensed source keeps its own measured depth
            disp.append(float(ray @ ray) / (float(ray @ v0.points[i0]) if sensed else proj))
            roots.append(root)
            for s, c, uv in obs:
                o_t.append(t)
                o_s.append(s)
                o_c.append(c)
                o_uv.append(uv)
        if not src_slot:
            return None, []
        prob = KeypointProblem(np.array(src_slot), np.array(src_cam), np.array(rays), np.array(disp), np.array(o_t), np.array(o_s), np.array(o_c), np.array(o_uv, np.float64), np.full(len(o_t), self.weight), np.array(held, bool))
        return prob, roots

    def _initial_point(self, nodes, views_of, poses, T_b_c, depth_at):
        """A track's world point from the first node with its own depth (sensor, stereo),
        else from the solved depth of the first node that has one; None if no node has any."""
        for k, c, i in nodes:
            P = views_of(k)[c].points[i]
            if np.isfinite(P[0]):
                T = poses[k] @ T_b_c[c]
                return T[:3, :3] @ P + T[:3, 3]
        if depth_at is not None:
            for k, c, i in nodes:
                v = views_of(k)[c]
                z = float(depth_at(k, c, v.uv[i : i + 1])[0])
                if z > 0:
                    T = poses[k] @ T_b_c[c]
                    return T[:3, :3] @ (v.rays[i] * z) + T[:3, 3]
        return None

    def update(self, prob: KeypointProblem, roots: list, window, poses: np.ndarray, T_b_c: np.ndarray) -> None:
        """Read the solved points back (world frame) from ``prob``'s source depths and ``poses``."""
        for t, root in enumerate(roots):
            d = prob.disp[t]
            if d <= 0:
                continue
            T = poses[window[prob.src_slot[t]]] @ T_b_c[prob.src_cam[t]]
            self.points[root] = T[:3, :3] @ (prob.rays[t] / d) + T[:3, 3]

    def retain(self, keyframes) -> None:
        """Forget every node outside ``keyframes`` (their tracks and solved points stay with
        the nodes kept), so that a tracker of every frame holds only its recent frames.
        Node ids are renumbered in the order they were added; a track's root stays its
        oldest node kept."""
        keep = set(keyframes)
        views = sorted((b, k, c) for (k, c), b in self.base.items() if k in keep)
        new_of, nodes, base, count = {}, [], {}, {}
        for b, k, c in views:
            base[(k, c)], count[(k, c)] = len(nodes), self.count[(k, c)]
            for i in range(self.count[(k, c)]):
                new_of[b + i] = len(nodes)
                nodes.append((k, c, i))
        parent, points, root_of = list(range(len(nodes))), {}, {}
        for old, new in new_of.items():  # ascending: the first node met of a track is its new root
            r = self._find(old)
            if r not in root_of:
                root_of[r] = new
                if r in self.points:
                    points[new] = self.points[r]
            parent[new] = root_of[r]
        self.base, self.count, self.nodes, self.parent, self.points = base, count, nodes, parent, points

    def state_arrays(self, prefix: str = "tracks.") -> dict:
        """The tracks as arrays for a checkpoint (nodes come back from the keyframes' keypoints)."""
        roots = np.array(sorted(self.points), np.int64)
        return {prefix + "parent": np.array(self.parent, np.int64), prefix + "roots": roots, prefix + "points": np.array([self.points[r] for r in roots], np.float64).reshape(-1, 3)}

    def load_state_arrays(self, a: dict, prefix: str = "tracks.") -> None:
        """Restore :meth:`state_arrays` once :meth:`add_views` has made the same nodes again."""
        parent = a[prefix + "parent"]
        if len(parent) != len(self.parent):
            raise ValueError(f"checkpoint tracks have {len(parent)} keypoints, the keyframes {len(self.parent)}")
        self.parent = [int(v) for v in parent]
        self.points = {int(r): p for r, p in zip(a[prefix + "roots"], a[prefix + "points"])}
