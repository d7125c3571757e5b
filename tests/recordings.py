"""A Rerun recording (``.rrd``) read back for the tests of ``--rerun`` (tests/cli/test_rerun_cli.py) and of
:mod:`crfdepth.pictures.rerun_recording` (tests/pictures/test_rerun_recording.py).

rerun-sdk 0.41 reads a file with ``rerun.chunk.RrdReader(path).stream().to_chunks()``: each chunk holds the
rows of one entity path as an Arrow record batch, one column per timeline (``frame``, ``stamp``, ``log_time``)
and one per component (``Pinhole:image_from_camera``, ``DepthImage:buffer`` ...), each cell the component's
instances. :func:`read_recording` gathers them per entity and time step; :func:`depth_image`,
:func:`pinhole_K` and :func:`pose` decode the components the tests compare.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

Recording = dict[str, dict[int | None, dict[str, np.ndarray | list]]]
"""``{entity path: {frame (None: static): {component column: value}}}``."""


def _array(values) -> np.ndarray | list:
    """An Arrow array as numpy: (N, k) for N fixed-size k-vectors, a list of dicts for structs, else (N,)."""
    import pyarrow as pa

    if pa.types.is_fixed_size_list(values.type):
        return values.flatten().to_numpy(zero_copy_only=False).reshape(len(values), values.type.list_size)
    if pa.types.is_struct(values.type):
        return values.to_pylist()
    return values.to_numpy(zero_copy_only=False)


def _value(cell) -> np.ndarray | list:
    """A component cell: its instances as :func:`_array` gives them; a cell of one list (a blob's bytes, a line
    strip's points) as that list's array."""
    import pyarrow as pa

    values = cell.values
    return _array(values[0].values) if pa.types.is_list(values.type) else _array(values)


def read_recording(path: Path, timeline: str = "frame") -> Recording:
    """Every entity of the ``.rrd`` file at ``path`` with its components per time step of ``timeline`` (``frame``;
    ``stamp``: nanoseconds) (static rows under None); entity paths without the leading ``/``; rows of one step
    merged."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    found: Recording = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        steps = batch.column(timeline).cast(pa.int64()) if timeline in names else None
        frames = steps.to_pylist() if steps is not None else [None] * batch.num_rows
        for row, frame in enumerate(frames):
            step = found.setdefault(chunk.entity_path.lstrip("/"), {}).setdefault(frame, {})
            for name in (n for n in names if ":" in n):
                cell = batch.column(name)[row]
                if cell.is_valid:
                    step[name] = _value(cell)
    return found


def depth_image(step: dict) -> np.ndarray:
    """The (H, W) float32 metres of a ``DepthImage`` logged with ``meter=1``."""
    (fmt,) = step["DepthImage:format"]
    assert float(step["DepthImage:meter"][0]) == 1.0
    values = np.frombuffer(step["DepthImage:buffer"].tobytes(), dtype=np.float32)
    return values.reshape(fmt["height"], fmt["width"])


def pinhole_K(step: dict) -> np.ndarray:
    """The (3, 3) ``image_from_camera`` of a ``Pinhole`` (stored column-major)."""
    return step["Pinhole:image_from_camera"][0].reshape(3, 3).T


def pose(step: dict) -> np.ndarray:
    """The (4, 4) ``T_world_cam`` of a ``Transform3D`` logged with ``mat3x3`` and ``translation``."""
    T = np.eye(4)
    T[:3, :3] = step["Transform3D:mat3x3"][0].reshape(3, 3).T
    T[:3, 3] = step["Transform3D:translation"][0]
    return T
