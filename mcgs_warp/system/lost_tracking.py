"""The tracker's books of keyframes it could not track (:class:`~mcgs_warp.system.tracker.Tracker`):
lost ones (not mapped, no sweep or relocalization source) and kept ones (held at their start
by MCBA after a failed dense solve), with the constant-velocity carry and the open lost span
that one warning line reports once tracking resumes (:meth:`LostTracking.update`).

Inputs: per keyframe whether it is tracked and its frame index. State: the books, which a
checkpoint carries as JSON (:meth:`LostTracking.state`, :meth:`LostTracking.load_state`).
"""

from __future__ import annotations


class LostTracking:
    """The lost and kept keyframes (module docstring)."""

    def __init__(self):
        self.lost: list = []  # keyframes whose tracking was lost (:meth:`update`): not mapped
        self.kept: list = []  # keyframes whose dense solve failed twice where keypoints placed them or constant velocity carries them (not lost ones): MCBA holds that start and drops their temporal correspondences from then on (the tracker's recovery)
        self.carried = False  # the last keyframe kept the constant-velocity prediction
        self.span = None  # the open lost span [first frame, last frame, keyframes]

    def update(self, k: int, frame: int, tracked: bool) -> None:
        """Lost tracking: constant velocity carries the pose through one failed keyframe at
        most. A second one in a row that nothing relocalizes is lost, and so is every one
        after it until a keyframe tracks again: lost keyframes keep the prediction (the
        trajectory needs a pose) but are not mapped, and the span gets one warning line when
        tracking resumes (or at the end, :meth:`close_span`). ``frame``: keyframe ``k``'s."""
        if tracked:
            self.carried = False
            self.close_span(resumed_at=frame)
            return
        if self.carried:
            self.lost.append(k)
            self.span = [frame if self.span is None else self.span[0], frame, (0 if self.span is None else self.span[2]) + 1]
        self.carried = True

    def close_span(self, resumed_at: int | None = None) -> None:
        """Say that tracking was lost (one warning line with the span), once it has ended."""
        from ..errors import warn

        if self.span is None:
            return
        a, b, n = self.span
        end = f"tracking resumed at frame {resumed_at}" if resumed_at is not None else "it never resumed"
        warn(None, f"frames {a}-{b} ({n} keyframe{'s' if n > 1 else ''}): tracking lost, nothing relocalized them; their poses are the constant-velocity prediction and they are not mapped; {end}")
        self.span = None

    def state(self) -> dict:
        """The state as JSON-ready values (the tracker's checkpoint books)."""
        return {"lost": self.lost, "kept": self.kept, "carried": self.carried, "lost_span": self.span}

    def load_state(self, books: dict) -> None:
        """Restore :meth:`state`."""
        self.lost, self.kept = [int(k) for k in books["lost"]], [int(k) for k in books["kept"]]
        self.carried, self.span = bool(books["carried"]), books["lost_span"]
