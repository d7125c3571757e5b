"""The transform tree of a ROS recording: ``/tf_static`` and ``/tf``, composed like tf2 (docs/design.md section 1).

A ``geometry_msgs/msg/TransformStamped`` with ``header.frame_id`` P (the parent) and
``child_frame_id`` C gives ``T_P_C``: the 4x4 rigid transform (metres) that maps points
expressed in C into P, ``p_P = R p_C + t``. :class:`TransformTree` collects these edges
and answers ``lookup(target, source)`` = ``T_target_source`` by composing the edges along
the tree through the lowest common ancestor, so ``lookup("camera_optical", "velodyne")``
is the ``T_cam_lidar`` of a rig calibration.

Rules, as in tf2:

- frame names are normalised by stripping leading ``/`` (ROS 1 tf allowed
  ``/velodyne``; tf2 uses ``velodyne``);
- every frame has at most one parent, and the edges form a forest (no cycles);
- edges from ``/tf_static`` are timeless, a later one for the same child replaces the
  earlier; edges from ``/tf`` keep every sample, sorted by stamp, and are interpolated
  at the requested stamp (translation linearly, rotation by Slerp), held at the first or
  last sample outside their recorded range; no stamp means the latest sample;
- a child published on both ``/tf_static`` and ``/tf`` is refused when a lookup needs it.

Quaternions are scalar-last ``(x, y, z, w)`` as in ROS and in
:meth:`scipy.spatial.transform.Rotation.from_quat`, and are normalised on entry.
Messages are read by duck typing: nothing here imports ``rosbags``, so this module works
without the optional ``ros`` extra. Every failure is a :class:`TransformError` (an
:class:`~crfdepth.errors.InputError`) with one line naming the frames involved.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from crfdepth.errors import InputError
from crfdepth.geometry.rigid import invert_rigid

__all__ = ["TransformError", "TransformTree"]

_log = logging.getLogger(__name__)

_TOPICS = "/tf_static or /tf"
# Most frame names one error message lists, in all and per connected group.
_MAX_NAMES = 20
_MAX_NAMES_PER_GROUP = 10
# A quaternion whose norm is further than this from 1 is normalised with a warning.
_QUATERNION_TOLERANCE = 1e-3


class TransformError(InputError):
    """A transform that cannot be stored or looked up: bad values, two parents, no connection."""


@dataclass
class _Samples:
    """The ``/tf`` samples of one edge; sorted arrays are built on first use after an addition."""

    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)
    quaternions: list[np.ndarray] = field(default_factory=list)
    _sorted: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)

    def append(self, stamp_ns: int, translation: np.ndarray, quaternion: np.ndarray) -> None:
        self.stamps.append(stamp_ns)
        self.translations.append(translation)
        self.quaternions.append(quaternion)
        self._sorted = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stamps (N,) int64 ns, translations (N, 3), quaternions (N, 4); one sample per stamp, the last added."""
        if self._sorted is None:
            stamps = np.asarray(self.stamps, dtype=np.int64)
            order = np.argsort(stamps, kind="stable")
            stamps = stamps[order]
            # Of equal stamps keep the last added (the stable sort keeps insertion order).
            keep = np.ones(len(stamps), dtype=bool)
            keep[:-1] = stamps[1:] != stamps[:-1]
            order = order[keep]
            self._sorted = (stamps[keep], np.stack(self.translations)[order], np.stack(self.quaternions)[order])
        return self._sorted

    def at(self, stamp_ns: int | None) -> np.ndarray:
        """(4, 4) ``T_parent_child`` at ``stamp_ns`` (None: the latest), interpolated or held."""
        stamps, translations, quaternions = self.arrays()
        if stamp_ns is None or stamp_ns >= stamps[-1]:
            return _matrix(translations[-1], quaternions[-1])
        if stamp_ns <= stamps[0]:
            return _matrix(translations[0], quaternions[0])
        i1 = int(np.searchsorted(stamps, stamp_ns, side="right"))
        i0 = i1 - 1
        alpha = (stamp_ns - int(stamps[i0])) / (int(stamps[i1]) - int(stamps[i0]))
        translation = (1.0 - alpha) * translations[i0] + alpha * translations[i1]
        from scipy.spatial.transform import Rotation, Slerp  # at first use: SciPy's import is 0.2 s

        rotation = Slerp([0.0, 1.0], Rotation.from_quat(quaternions[i0:i1 + 1]))(alpha)
        T = np.eye(4)
        T[:3, :3] = rotation.as_matrix()
        T[:3, 3] = translation
        return T


def _matrix(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """(4, 4) float64 rigid transform from a translation (3,) and a unit quaternion (x, y, z, w)."""
    from scipy.spatial.transform import Rotation  # at first use: SciPy's import is 0.2 s

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    T[:3, 3] = translation
    return T


def _frame(name: object, what: str) -> str:
    """A frame name without leading ``/``; an empty or non-string name is refused."""
    if not isinstance(name, str):
        raise TransformError(f"{what}: expected a frame name (str), got {type(name).__name__} {name!r}")
    frame = name.lstrip("/")
    if not frame:
        raise TransformError(f"{what}: expected a non-empty frame name, got {name!r}")
    return frame


def _vector(values: object, size: int, what: str) -> np.ndarray:
    """(size,) finite float64 copy of ``values``."""
    try:
        vector = np.array(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TransformError(f"{what}: expected {size} numbers, got {type(values).__name__} {values!r}") from None
    if vector.shape != (size,):
        raise TransformError(f"{what}: expected {size} numbers, got {vector.size}")
    if not np.all(np.isfinite(vector)):
        raise TransformError(f"{what}: expected finite numbers, got {' '.join(f'{v:g}' for v in vector)}")
    return vector


def _names(frames: list[str], limit: int) -> str:
    """``a, b, c`` with at most ``limit`` names, then ``... and N more``."""
    shown = ", ".join(frames[:limit])
    return shown if len(frames) <= limit else f"{shown} ... and {len(frames) - limit} more"


class TransformTree:
    """The frames and transforms of ``/tf_static`` and ``/tf``: add edges, look up composed transforms.

    Example::

        tree = TransformTree()
        for msg in static_messages:
            tree.add_message(msg, static=True)
        for msg in dynamic_messages:
            tree.add_message(msg, static=False)
        T_cam_lidar = tree.lookup("camera_optical", "velodyne", stamp_ns)   # (4, 4) float64
    """

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}           # child -> parent
        self._static: dict[str, np.ndarray] = {}     # child -> (4, 4) T_parent_child
        self._dynamic: dict[str, _Samples] = {}      # child -> its /tf samples
        self._frames: set[str] = set()

    def add(self, parent: str, child: str, translation, quaternion_xyzw, stamp_ns: int, *,
            static: bool) -> None:
        """Store the edge ``T_parent_child`` (maps points in ``child`` into ``parent``).

        Args:
            parent: the parent frame (``header.frame_id``); a leading ``/`` is ignored.
            child: the child frame (``child_frame_id``); a leading ``/`` is ignored.
            translation: (3,) the child's origin in the parent frame, metres, finite.
            quaternion_xyzw: (4,) the child's orientation in the parent frame, scalar last,
                non-zero and finite; normalised here.
            stamp_ns: the header stamp, integer nanoseconds (ignored for a static edge).
            static: True for ``/tf_static`` (timeless: replaces an earlier static edge of
                this child), False for ``/tf`` (one more sample of this child's edge).

        Raises:
            TransformError: ``parent == child``; ``child`` already has another parent; the
                edge would close a cycle; a non-finite translation; a zero or non-finite
                quaternion; a stamp that is not an integer.
        """
        parent, child = _frame(parent, "parent"), _frame(child, "child")
        edge = f"transform {parent!r} -> {child!r}"
        if parent == child:
            raise TransformError(f"{edge}: expected a child frame different from its parent, got {child!r} for both")
        translation = _vector(translation, 3, f"{edge}: translation")
        quaternion = _vector(quaternion_xyzw, 4, f"{edge}: quaternion (x, y, z, w)")
        norm = float(np.linalg.norm(quaternion))
        if norm == 0.0:
            raise TransformError(f"{edge}: expected a non-zero quaternion (x, y, z, w), got 0 0 0 0")
        if abs(norm - 1.0) > _QUATERNION_TOLERANCE:
            _log.warning("%s: quaternion norm %.6g is not 1; normalised", edge, norm)
        quaternion = quaternion / norm
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer)):
            raise TransformError(f"{edge}: stamp_ns: expected an integer number of nanoseconds, got "
                                 f"{type(stamp_ns).__name__} {stamp_ns!r}")
        known = self._parent.get(child)
        if known is not None and known != parent:
            raise TransformError(f"frame {child!r} has two parents in {_TOPICS}: {known!r} and {parent!r} (tf2 allows "
                                 f"one parent per frame; the recording mixes two transform trees)")
        if known is None:
            ancestors = self._ancestors(parent)
            if child in ancestors:
                loop = " -> ".join(reversed([child] + ancestors[:ancestors.index(child) + 1]))
                raise TransformError(f"{edge}: closes a cycle in the transform tree ({loop}); frames must form a tree")
        self._parent[child] = parent
        self._frames.update((parent, child))
        if static:
            self._static[child] = _matrix(translation, quaternion)
        else:
            self._dynamic.setdefault(child, _Samples()).append(int(stamp_ns), translation, quaternion)

    def add_message(self, msg, *, static: bool) -> None:
        """Store every ``TransformStamped`` of a ``tf2_msgs/msg/TFMessage`` (ROS 1 or ROS 2).

        ``msg.transforms[i]`` needs ``header.frame_id``, ``header.stamp.sec``,
        ``header.stamp.nanosec``, ``child_frame_id``, ``transform.translation.{x,y,z}`` and
        ``transform.rotation.{x,y,z,w}``, as rosbags' deserialised messages have.
        ``static``: True for ``/tf_static``, False for ``/tf`` (see :meth:`add`).
        """
        transforms = getattr(msg, "transforms", None)
        if transforms is None:
            raise TransformError(f"{_TOPICS} message: expected a tf2_msgs/msg/TFMessage with a 'transforms' list, "
                                 f"got {type(msg).__name__}")
        for stamped in transforms:
            try:
                header, t = stamped.header, stamped.transform
                parent, child = header.frame_id, stamped.child_frame_id
                stamp_ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
                translation = (t.translation.x, t.translation.y, t.translation.z)
                quaternion = (t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w)
            except AttributeError as error:
                raise TransformError(f"{_TOPICS} message: expected geometry_msgs/msg/TransformStamped entries, got "
                                     f"{type(stamped).__name__} without {error.name!r}") from None
            self.add(parent, child, translation, quaternion, stamp_ns, static=static)

    @property
    def frames(self) -> list[str]:
        """Sorted names of every frame seen, parents and children (without leading ``/``)."""
        return sorted(self._frames)

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> np.ndarray:
        """(4, 4) float64 ``T_target_source``: maps points in frame ``source`` into frame ``target``.

        ``p_target = T[:3, :3] @ p_source + T[:3, 3]``. Composed along the tree through the
        lowest common ancestor (either frame may be an ancestor of the other; ``target ==
        source`` gives the identity). ``/tf`` edges are taken at ``stamp_ns`` (integer
        nanoseconds): interpolated between the samples around it, held at the first or
        last sample outside the recorded range, the latest sample when ``stamp_ns`` is None.
        ``/tf_static`` edges ignore ``stamp_ns``.

        Raises:
            TransformError: the frames are not connected (the message says which frame was
                never seen and lists the connected groups of frames), or a frame on the way
                is published on both ``/tf_static`` and ``/tf``.
        """
        up, down = self._chain(target, source)
        return invert_rigid(self._compose(down, stamp_ns)) @ self._compose(up, stamp_ns)

    def path(self, target: str, source: str) -> list[str]:
        """Frame names along the chain from ``source`` to ``target``, both included (same errors as :meth:`lookup`)."""
        up, down = self._chain(target, source)
        if up:
            lca = self._parent[up[-1]]
        elif down:
            lca = self._parent[down[-1]]
        else:
            lca = _frame(source, "source")
        return up + [lca] + list(reversed(down))

    def has_dynamic(self, target: str, source: str) -> bool:
        """Whether the chain from ``source`` to ``target`` uses any ``/tf`` (time-varying) edge."""
        up, down = self._chain(target, source)
        return any(child in self._dynamic for child in up + down)

    def root(self, frame: str) -> str:
        """The top of ``frame``'s tree (the frame itself when it has no parent or is unknown)."""
        return self._ancestors(_frame(frame, "frame"))[-1]

    def dynamic_span(self, target: str, source: str) -> tuple[int, int] | None:
        """``(first, last)`` stamps (ns) that every ``/tf`` edge on the chain from ``source`` to ``target``
        has samples around (outside it a lookup holds the first or last sample); None when the chain is
        static."""
        up, down = self._chain(target, source)
        spans = [self._dynamic[child].arrays()[0] for child in up + down if child in self._dynamic]
        if not spans:
            return None
        return max(int(s[0]) for s in spans), min(int(s[-1]) for s in spans)

    # -- internals ---------------------------------------------------------------------

    def _ancestors(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to its root, in order (the walk is bounded)."""
        chain = [frame]
        for _ in range(len(self._parent) + 1):
            parent = self._parent.get(chain[-1])
            if parent is None:
                return chain
            chain.append(parent)
        raise TransformError(f"frame {frame!r}: the walk to the root of the transform tree does not end "
                             f"({' -> '.join(chain[:_MAX_NAMES])} ...): the frames form a cycle")

    def _chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Children of the edges from ``source`` up to the common ancestor, and from ``target`` up to it."""
        target, source = _frame(target, "target"), _frame(source, "source")
        if target == source:
            return [], []
        up, down = self._ancestors(source), self._ancestors(target)
        common = set(down)
        for i, frame in enumerate(up):
            if frame in common:
                j = down.index(frame)
                edges = up[:i] + down[:j]
                both = [child for child in edges if child in self._static and child in self._dynamic]
                if both:
                    raise TransformError(
                        f"no transform from frame {source!r} to frame {target!r}: frame {both[0]!r} is published on "
                        f"both /tf_static and /tf (parent {self._parent[both[0]]!r}); tf2 would use only one of them")
                return up[:i], down[:j]
        raise TransformError(self._disconnected(target, source))

    def _compose(self, children: list[str], stamp_ns: int | None) -> np.ndarray:
        """``T_top_first``: the edges above ``children`` (ordered upward) composed, top = last child's parent."""
        T = np.eye(4)
        for child in children:
            T = self._edge(child, stamp_ns) @ T
        return T

    def _edge(self, child: str, stamp_ns: int | None) -> np.ndarray:
        """(4, 4) ``T_parent_child`` of the edge above ``child``."""
        static = self._static.get(child)
        return static if static is not None else self._dynamic[child].at(stamp_ns)

    def _disconnected(self, target: str, source: str) -> str:
        """The one-line message for two frames with no chain between them."""
        message = f"no transform from frame {source!r} to frame {target!r} in {_TOPICS}: "
        unknown = [frame for frame in dict.fromkeys((source, target)) if frame not in self._frames]
        if len(unknown) == 2:
            message += f"frames {unknown[0]!r} and {unknown[1]!r} are unknown (never seen)"
        elif unknown:
            message += f"frame {unknown[0]!r} is unknown (never seen)"
        else:
            message += "the frames are not connected"
        return f"{message}; frames with transforms: {self._groups()}"

    def _groups(self) -> str:
        """The connected groups of frames, ``{root, child, ...}, {...}``, at most ~20 names in all."""
        if not self._frames:
            return "none (no /tf_static or /tf message was read)"
        members: dict[str, list[str]] = {}
        for frame in sorted(self._frames):
            members.setdefault(self._ancestors(frame)[-1], []).append(frame)
        groups = sorted(members.items(), key=lambda item: (-len(item[1]), item[0]))
        parts, budget = [], _MAX_NAMES
        for k, (root, frames) in enumerate(groups):
            if budget <= 0:
                parts.append(f"... and {len(groups) - k} more groups")
                break
            ordered = [root] + [frame for frame in frames if frame != root]
            limit = min(_MAX_NAMES_PER_GROUP, budget)
            parts.append("{" + _names(ordered, limit) + "}")
            budget -= min(limit, len(ordered))
        return ", ".join(parts)

