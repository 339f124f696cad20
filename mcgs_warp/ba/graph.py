"""The factor graph: the MCBA edges of a keyframe buffer, which are active, and their
correspondences (computed once, kept for reuse, checkpointed in segment files).

Which edges exist is chosen in :mod:`mcgs_warp.ba.edges` (view overlap) and
:mod:`mcgs_warp.ba.loops` (revisits); this module only keeps the books.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..buffer import KeyframeBuffer
from .edges import CROSS_TIME, LOOP, TEMPORAL, GraphConfig, _as_edges, _edge_kind, overlap_edges
from .loops import confirm_loops, loop_candidates


class FactorGraph:
    """The MCBA edges of a keyframe buffer and their correspondences (in the spirit of
    DROID-SLAM's ``FactorGraph``).

    An edge is a key ``(i, ci, j, cj)`` with a kind (TEMPORAL, CROSS_VIEW, CROSS_TIME, LOOP).
    Every edge the graph knows is either *active* (part of the next MCBA problem,
    :meth:`arrays`) or *stored* (taken out of the problem, e.g. when it left the online
    window, with its correspondences kept for later reuse, as DROID keeps inactive edges
    for global BA). Correspondences per edge: ``targets`` [h,w,2] float32 (reduced-grid
    pixels of view (j, cj)) and ``weights`` [h,w] float32 in [0,1], as a
    :class:`~mcgs_warp.frontend.flow.FlowProvider` returns them; an edge may be active before
    they are computed (:meth:`missing`, :meth:`compute`). Keyframe indices are buffer
    indices; nothing renumbers them.

    ``rig_overlap`` [C,C] (:func:`camera_overlap`) links cameras for cross-view edges."""

    def __init__(self, buffer: KeyframeBuffer, rig_overlap: np.ndarray | None = None, config: GraphConfig | None = None):
        self.buf = buffer
        self.rig_overlap = rig_overlap
        self.cfg = config or GraphConfig()
        self._kind: dict = {}  # key -> kind, every known edge (insertion order)
        self._active: dict = {}  # key -> None: the active edges, in insertion order
        self._corr: dict = {}  # key -> (targets [h,w,2], weights [h,w])
        self._leaving: dict = {}  # keyframe i -> {key: None}: edges with correspondences leaving i
        self._saved: dict = {}  # key -> (segment, row): where the checkpoint store holds its current correspondences
        self._store: Path | None = None  # the folder _saved refers to
        self._seg_rows: dict = {}  # segment -> rows written to it

    # ---- membership --------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._active)

    def __contains__(self, key) -> bool:
        return tuple(int(v) for v in key[:4]) in self._active

    @property
    def edges(self) -> np.ndarray:
        """Active edges [E,5] int32 ``(i, ci, j, cj, kind)`` in the order they were added."""
        return self._rows(self._active)

    @property
    def stored(self) -> np.ndarray:
        """Edges [S,5] known but not active (their correspondences are kept)."""
        return self._rows(k for k in self._kind if k not in self._active)

    def _rows(self, keys) -> np.ndarray:
        return np.array([(*k, self._kind[k]) for k in keys], dtype=np.int32).reshape(-1, 5)

    @staticmethod
    def _keys(edges) -> list:
        return [tuple(int(v) for v in row[:4]) for row in _as_edges(edges)]

    def add(self, edges, targets=None, weights=None) -> np.ndarray:
        """Activate ``edges`` [E,4|5] (kind from column 4, else inferred: same keyframe ->
        cross-view, same camera -> temporal, otherwise cross-time). With ``targets``
        [E,h,w,2] and ``weights`` [E,h,w] their correspondences are stored too (replacing
        older ones); a stored edge comes back with its kept correspondences. Returns the
        edges [N,5] that were not active before."""
        e = _as_edges(edges)
        keys = self._keys(e)
        if targets is not None:
            self.set_correspondences(e, targets, weights)
        new = []
        for n, k in enumerate(keys):
            if k not in self._kind or e.shape[1] > 4:
                self._kind[k] = int(e[n, 4]) if e.shape[1] > 4 else _edge_kind(*k)
            if k not in self._active:
                self._active[k] = None
                new.append(k)
        return self._rows(new)

    def remove(self, edges=None, keyframes=None, outside=None, kinds=None, store: bool = True) -> np.ndarray:
        """Take active edges out of the problem: those in ``edges`` [E,>=4], touching a
        keyframe in ``keyframes``, or with an end outside the window ``outside`` (keyframes
        that stay), restricted to ``kinds`` if given. ``store`` keeps them (and their
        correspondences) for later reuse; ``store=False`` forgets them. Returns the removed
        edges [R,5]."""
        sel = set(self._active)
        if edges is not None:
            sel &= set(self._keys(edges))
        if keyframes is not None:
            ks = {int(k) for k in keyframes}
            sel = {k for k in sel if k[0] in ks or k[2] in ks}
        if outside is not None:
            win = {int(k) for k in outside}
            sel = {k for k in sel if k[0] not in win or k[2] not in win}
        if kinds is not None:
            sel = {k for k in sel if self._kind[k] in set(kinds)}
        gone = [k for k in self._active if k in sel]
        rows = self._rows(gone)
        for k in gone:
            del self._active[k]
            if not store:
                del self._kind[k]
                self._drop_corr(k)
        return rows

    def forget_keyframes(self, keyframes) -> int:
        """Drop every edge (active or stored) touching ``keyframes``, with its
        correspondences (the keyframes left the buffer or were re-initialized). Returns the count."""
        ks = {int(k) for k in keyframes}
        return self.forget(self._rows([k for k in self._kind if k[0] in ks or k[2] in ks]))

    # ---- correspondences ---------------------------------------------------------------
    def has_correspondences(self, key) -> bool:
        return tuple(int(v) for v in key[:4]) in self._corr

    def missing(self, edges=None) -> np.ndarray:
        """Edges [M,5] among ``edges`` (default: the active ones) without correspondences."""
        keys = list(self._active) if edges is None else self._keys(edges)
        return self._rows_known(k for k in dict.fromkeys(keys) if k not in self._corr)

    def set_correspondences(self, edges, targets, weights) -> None:
        """Store ``targets`` [E,h,w,2] and ``weights`` [E,h,w] for ``edges`` [E,>=4] (known
        edges keep their activity; unknown ones become stored edges)."""
        keys = self._keys(edges)
        t = np.asarray(targets, dtype=np.float32)
        w = np.asarray(weights, dtype=np.float32)
        shape = (len(keys), self.buf.h, self.buf.w)
        if t.shape != shape + (2,) or w.shape != shape:
            raise ValueError(f"targets/weights must be {shape + (2,)} / {shape}, got {t.shape} / {w.shape}")
        for n, k in enumerate(keys):
            self._kind.setdefault(k, _edge_kind(*k))
            self._corr[k] = (t[n].copy(), w[n].copy())
            self._leaving.setdefault(k[0], {})[k] = None
            self._saved.pop(k, None)  # changed: the next checkpoint writes it again

    def _drop_corr(self, key) -> None:
        if self._corr.pop(key, None) is not None:
            self._leaving[key[0]].pop(key, None)
            self._saved.pop(key, None)

    def measured_weight(self, keyframe: int, n_cameras: int) -> np.ndarray:
        """[C,h,w] float32: summed correspondence confidence of every edge (active or stored)
        leaving each grid pixel of ``keyframe`` (which of its pixels something measured).
        Indexed by source keyframe: the cost grows with that keyframe's edges, not the graph's."""
        out = np.zeros((n_cameras, self.buf.h, self.buf.w), np.float32)
        for k in self._leaving.get(int(keyframe), ()):
            out[k[1]] += self._corr[k][1]
        return out

    def correspondences(self, edges=None):
        """Stacked ``targets`` [E,h,w,2] and ``weights`` [E,h,w] of ``edges`` (default: the
        active ones); KeyError when some have none (see :meth:`missing`)."""
        keys = list(self._active) if edges is None else self._keys(edges)
        absent = [k for k in keys if k not in self._corr]
        if absent:
            raise KeyError(f"no correspondences for {len(absent)} edge(s), e.g. {absent[0]}; compute them first")
        if not keys:
            return np.zeros((0, self.buf.h, self.buf.w, 2), np.float32), np.zeros((0, self.buf.h, self.buf.w), np.float32)
        return np.stack([self._corr[k][0] for k in keys]), np.stack([self._corr[k][1] for k in keys])

    def compute(self, provider, edges=None) -> np.ndarray:
        """Compute and store correspondences with ``provider`` (``correspondences(buffer,
        edges [E,4] int32) -> (targets, weights)``) for ``edges`` [E,>=4], replacing any kept
        ones (default: the active edges that have none). Returns the edges computed [N,5]."""
        rows = self.missing() if edges is None else self._rows_of(edges)
        if len(rows):
            t, w = provider.correspondences(self.buf, np.ascontiguousarray(rows[:, :4], dtype=np.int32))
            self.set_correspondences(rows, t, w)
        return rows

    def _rows_of(self, edges) -> np.ndarray:
        return self._rows_known(dict.fromkeys(self._keys(edges)))

    def _rows_known(self, keys) -> np.ndarray:
        """Rows [N,5] of ``keys``, the kind inferred for edges the graph does not know (asking
        about an edge does not add it)."""
        return np.array([(*k, self._kind.get(k, _edge_kind(*k))) for k in keys], dtype=np.int32).reshape(-1, 5)

    def forget(self, edges) -> int:
        """Drop ``edges`` [E,>=4] (active or stored) with their correspondences; returns the count."""
        gone = [k for k in self._keys(edges) if k in self._kind]
        for k in gone:
            self._active.pop(k, None)
            self._drop_corr(k)
            del self._kind[k]
        return len(gone)

    def refresh(self, provider, keyframes, kinds=(TEMPORAL, CROSS_TIME, LOOP)) -> np.ndarray:
        """Recompute with ``provider`` (e.g. :class:`GuidedDIS`, from the current geometry) the
        correspondences of the active edges of ``kinds`` touching ``keyframes``; cross-view
        edges are left alone by default (their rig geometry does not change), and so are edges
        the provider calls settled (``provider.settled(buffer, edges, targets, weights)``, if it
        has one: the current geometry already predicts their matches). Returns the edges
        recomputed [R,5]."""
        ks = {int(k) for k in keyframes}
        kinds = set(kinds)
        keys = [k for k in self._active if (k[0] in ks or k[2] in ks) and self._kind[k] in kinds]
        if keys and hasattr(provider, "settled"):  # edges the geometry already explains keep their matches
            known = [k for k in keys if k in self._corr]
            if known:
                t, w = self.correspondences(self._rows(known))
                settled = {k for k, done in zip(known, provider.settled(self.buf, self._rows(known), t, w)) if done}
                keys = [k for k in keys if k not in settled]
        return self.compute(provider, self._rows(keys)) if keys else np.zeros((0, 5), np.int32)

    def items(self):
        """Every edge with correspondences, active or stored: ``(edge [5] int32, targets
        [h,w,2], weights [h,w])`` (e.g. to see which pixels of a keyframe are measured)."""
        for k, (t, w) in self._corr.items():
            yield np.array((*k, self._kind[k]), np.int32), t, w

    def arrays(self, keyframes=None):
        """The MCBA problem: active ``edges`` [E,5] int32 (restricted to those with both ends
        in ``keyframes`` if given), ``targets`` [E,h,w,2] and ``weights`` [E,h,w] float32."""
        keys = list(self._active)
        if keyframes is not None:
            ks = {int(k) for k in keyframes}
            keys = [k for k in keys if k[0] in ks and k[2] in ks]
        edges = self._rows(keys)
        t, w = self.correspondences(edges)
        return edges, t, w

    # ---- edge choice -------------------------------------------------------------------
    def update_window(self, keyframes, cross_view: bool = True, cross_time: bool = False, max_gap: int | None = None, config=None) -> np.ndarray:
        """Make the active set the overlap-chosen edges among ``keyframes``
        (:func:`overlap_edges`, current geometry): active edges outside the window or no
        longer chosen are stored (loop edges inside the window stay); chosen ones are
        activated (with kept correspondences where known). Returns the edges [N,5] still
        without correspondences, for the caller to :meth:`compute` with its providers.
        ``config``: the edge choice's GraphConfig instead of the graph's own (global BA's)."""
        chosen = overlap_edges(self.buf, keyframes, self.rig_overlap, config or self.cfg, cross_view=cross_view, cross_time=cross_time, max_gap=max_gap)
        keep = set(self._keys(chosen))
        win = {int(k) for k in keyframes}
        drop = [k for k in self._active if not (k in keep or (self._kind[k] == LOOP and k[0] in win and k[2] in win))]
        self.remove(np.array(drop, dtype=np.int32).reshape(-1, 4))
        self.add(chosen)
        return self.missing()

    def link_to_previous(self, k: int, n_cameras: int) -> list:
        """A new keyframe ``k`` whose views overlap no one else's by the graph's measure (a
        fast turn, a poor constant-velocity start) would not be tracked at all: link each such
        camera to the previous keyframe's same camera both ways (temporal edges), as
        DROID-SLAM always keeps the nearest edge. Returns the cameras linked so."""
        linked = {int(ci) for i, ci, j, _cj, _kind in self.edges if i == k and j != k}
        lonely = [c for c in range(n_cameras) if c not in linked]
        if lonely:
            self.add([(k, c, k - 1, c, TEMPORAL) for c in lonely] + [(k - 1, c, k, c, TEMPORAL) for c in lonely])
        return lonely

    def close_loops(self, provider, keyframes=None) -> list:
        """Find revisits among ``keyframes`` (default: all) by pose proximity and overlap
        (:func:`loop_candidates`, skipping edges the graph already knows), confirm them with
        ``provider`` (:func:`confirm_loops`) and activate the accepted ones, both directions,
        with their correspondences. Returns the :class:`LoopCheck` of every candidate."""
        cand = loop_candidates(self.buf, keyframes, self.cfg, exclude=self._kind)
        edges, t, w, checks = confirm_loops(self.buf, cand, provider, self.cfg)
        if len(edges):
            self.add(edges, t, w)
        return checks

    # ---- checkpoints -------------------------------------------------------------------
    def state_arrays(self, store=None) -> dict:
        """Plain arrays for a checkpoint (``np.savez``): ``graph_edges`` [N,5] int32 (every
        known edge), ``graph_active`` [N] bool, ``graph_has_corr`` [N] bool, and the
        correspondences of the edges that have them, in order: inline as ``graph_targets``
        [M,h,w,2] / ``graph_weights`` [M,h,w] float32, or, with a ``store`` folder, as
        ``graph_segment`` / ``graph_row`` [M] int64 into segment files ``store/seg_<n>.npz``.
        A segment is written once, holding the correspondences that changed since the last
        call (not every edge every time) and the live rows of segments that had fallen below
        half live, so the folder stays within about twice the live data once
        :meth:`prune_store` has removed the segments nothing refers to any more."""
        keys = list(self._kind)
        corr = [k for k in keys if k in self._corr]
        h, w = self.buf.h, self.buf.w
        out = {
            "graph_edges": self._rows(keys),
            "graph_active": np.array([k in self._active for k in keys], bool),
            "graph_has_corr": np.array([k in self._corr for k in keys], bool),
        }
        if store is None:
            out["graph_targets"] = np.array([self._corr[k][0] for k in corr], np.float32).reshape(-1, h, w, 2)
            out["graph_weights"] = np.array([self._corr[k][1] for k in corr], np.float32).reshape(-1, h, w)
            return out
        from ..io import atomic_write

        if self._store != Path(store):  # another folder: it holds none of ours
            self._saved, self._store, self._seg_rows = {}, Path(store), {}
        fresh = [k for k in corr if k not in self._saved]
        if fresh:  # also move the live rows of segments now less than half live (they get pruned)
            live: dict = {}
            for sg, _ in self._saved.values():
                live[sg] = live.get(sg, 0) + 1
            sparse = {sg for sg, n in self._seg_rows.items() if live.get(sg, 0) < 0.5 * n}
            fresh += [k for k in corr if k in self._saved and self._saved[k][0] in sparse]
            seg = 1 + max(_segments(store), default=-1)  # above every file there (ours among them)
            with atomic_write(Path(store) / f"seg_{seg:06d}.npz", "wb") as f:
                np.savez(f, targets=np.array([self._corr[k][0] for k in fresh], np.float32), weights=np.array([self._corr[k][1] for k in fresh], np.float32))
            self._saved.update({k: (seg, n) for n, k in enumerate(fresh)})
            self._seg_rows[seg] = len(fresh)
        out["graph_segment"] = np.array([self._saved[k][0] for k in corr], np.int64)
        out["graph_row"] = np.array([self._saved[k][1] for k in corr], np.int64)
        return out

    def prune_store(self, store) -> int:
        """Delete the segment files of ``store`` that no edge's current correspondences are
        in (call after the checkpoint that stopped referring to them is in place). Returns the count."""
        used = {s for s, _ in self._saved.values()}
        gone = [n for n in _segments(store) if n not in used]
        for n in gone:
            self._seg_rows.pop(n, None)
            (Path(store) / f"seg_{n:06d}.npz").unlink(missing_ok=True)
        return len(gone)

    def load_state_arrays(self, arrays, store=None) -> None:
        """Restore the state written by :meth:`state_arrays` (replacing the current one);
        ``store``: the segment folder it was written with, if any."""
        e = np.asarray(arrays["graph_edges"]).reshape(-1, 5)
        active = np.asarray(arrays["graph_active"], bool)
        has = np.asarray(arrays["graph_has_corr"], bool)
        saved, seg_rows = {}, {}
        if "graph_segment" in arrays:
            if store is None:
                raise ValueError("the checkpoint keeps its correspondences in segment files: pass their folder")
            seg, row = np.asarray(arrays["graph_segment"]), np.asarray(arrays["graph_row"])
            if len(seg) != has.sum() or len(row) != has.sum():
                raise ValueError("inconsistent factor-graph arrays in the checkpoint")
            t = np.zeros((len(seg), self.buf.h, self.buf.w, 2), np.float32)
            w = np.zeros((len(seg), self.buf.h, self.buf.w), np.float32)
            for n in np.unique(seg):
                with np.load(Path(store) / f"seg_{int(n):06d}.npz") as z:
                    sel = seg == n
                    t[sel], w[sel] = z["targets"][row[sel]], z["weights"][row[sel]]
                    seg_rows[int(n)] = len(z["weights"])
            saved = {tuple(int(v) for v in r[:4]): (int(a), int(b)) for r, a, b in zip(e[has], seg, row)}
        else:
            t, w = np.asarray(arrays["graph_targets"]), np.asarray(arrays["graph_weights"])
        if len(active) != len(e) or len(has) != len(e) or len(t) != has.sum() or len(w) != has.sum():
            raise ValueError("inconsistent factor-graph arrays in the checkpoint")
        self._kind = {tuple(int(v) for v in row[:4]): int(row[4]) for row in e}
        self._active = {tuple(int(v) for v in row[:4]): None for row, a in zip(e, active) if a}
        self._corr, self._leaving, self._saved = {}, {}, {}  # set_correspondences fills the first two
        if has.any():
            self.set_correspondences(e[has], t, w)
        self._saved, self._store = saved, (Path(store) if saved else None)
        self._seg_rows = seg_rows

def _segments(store) -> list:
    """Segment numbers of the files ``seg_<n>.npz`` in ``store`` (none if it does not exist)."""
    folder = Path(store)
    return sorted(int(p.stem[4:]) for p in folder.glob("seg_*.npz")) if folder.is_dir() else []
