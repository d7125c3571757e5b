"""The key-value formats calibrations are written in, read with each key once.

KITTI's calibration text format: ``key: values`` lines, each value a row of numbers.

Every KITTI calibration file is written this way (a raw-data day's ``calib_cam_to_cam.txt``,
``calib_velo_to_cam.txt`` and ``calib_imu_to_velo.txt``, an object benchmark's
``calib/*.txt``), so the calibration readers (:mod:`crfdepth.io.calibration`, docs/design.md
section 1) and the IMU-to-Velodyne reader of the poses given
(:mod:`crfdepth.sequences.poses`, section 12) share :func:`read_key_values` and
:func:`entry_array`. A rig calibration's YAML or JSON mapping is read by :func:`read_mapping`.

A key given twice is refused naming the key and the file (KITTI's files never repeat one;
PyYAML and ``json`` would keep the last value silently), and so are YAML anchors and aliases
(a rig needs none, and a kilobyte of nested aliases, a "billion laughs", expands to
gigabytes), YAML nested deeper than ``MAX_YAML_DEPTH`` or holding more than
``MAX_YAML_NODES`` values (both checked on the parser's events, before anything is built).
Messages quote at most a short prefix of a key or value (:func:`quote_key`,
:func:`quote_value`). A failure is an :class:`~crfdepth.errors.InputError` naming the file.
"""

from __future__ import annotations

import json
import re
import reprlib
from pathlib import Path

import numpy as np
import yaml

from crfdepth.errors import InputError
from crfdepth.io.files import MAX_CALIBRATION_BYTES, read_text

__all__ = ["MAX_YAML_DEPTH", "MAX_YAML_NODES", "entry_array", "is_rig_file", "list_keys", "quote_key", "quote_value",
           "read_key_values", "read_mapping"]

# Keys listed in a message ("keys present: ..."), and characters of a key quoted, at most.
_LISTED_KEYS = 12
_QUOTED_CHARS = 40
# Deepest nesting of a calibration YAML (a rig needs 3: mapping, matrix, row), and most values
# (scalars, lists, mappings) in it (a rig with 14 distortion coefficients has 64).
MAX_YAML_DEPTH = 16
MAX_YAML_NODES = 1000
_YAML_BASE = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml's parser where PyYAML has it


def quote_key(key: object) -> str:
    """``'key'`` for messages, cut to 40 characters (``'aaaa...' (1048576 characters)``)."""
    text = str(key)
    if len(text) <= _QUOTED_CHARS:
        return repr(text)
    return f"{text[:_QUOTED_CHARS]!r}... ({len(text)} characters)"


def quote_value(value: object) -> str:
    """A short repr of ``value`` for messages (``[1, 1, 1, 1, 1, 1, ...]``), built without the whole
    repr of a huge value."""
    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxtuple, short.maxdict = 2, 6, 6, 4
    short.maxstring = short.maxother = short.maxlong = _QUOTED_CHARS
    try:
        return short.repr(value)
    except Exception:  # a repr that fails (an int of 100,000 digits): the type alone
        return type(value).__name__


def list_keys(keys) -> str:
    """Up to 12 keys, comma-separated (a long one cut to 40 characters), and how many more there are."""
    keys = [str(key) for key in keys]
    shown = ", ".join(key if len(key) <= _QUOTED_CHARS else f"{key[:_QUOTED_CHARS]}... ({len(key)} characters)"
                      for key in keys[:_LISTED_KEYS])
    return shown + (f" and {len(keys) - _LISTED_KEYS} more" if len(keys) > _LISTED_KEYS else "")


def read_key_values(path: Path, what: str) -> dict[str, str]:
    """``key: values`` lines of a KITTI calibration file (values kept as text).

    The file must be a regular text file of at most ``MAX_CALIBRATION_BYTES`` (1 MiB,
    :func:`crfdepth.io.files.read_text`), with at least one ``key: values`` line and each key
    once: a key given twice is refused naming the key, the file and both lines (which value
    is meant cannot be told; KITTI's files never repeat one).
    """
    entries, lines = {}, {}
    text = read_text(path, what, "'key: values' lines (a KITTI calibration)", max_bytes=MAX_CALIBRATION_BYTES)
    for number, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("#"):  # a comment (e.g. of a rig YAML given by mistake)
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if sep and key:
            if key in entries:
                raise InputError(f"{what}: expected each key once in {path}, got {quote_key(key)} twice (lines "
                                 f"{lines[key]} and {number}): which value is meant cannot be told")
            entries[key], lines[key] = value.strip(), number
    if not entries:
        raise InputError(f"{what}: expected 'key: values' lines in {path}, found none")
    return entries


def entry_array(entries: dict[str, str], key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    """Entry ``key`` of a calibration file as a float64 array of ``shape``."""
    if key not in entries:
        raise InputError(f"calibration: key '{key}' not found in {path} (keys present: "
                         f"{list_keys(sorted(entries))})")
    count = int(np.prod(shape))
    tokens = entries[key].split()
    if len(tokens) != count:  # before converting: a line of a million tokens is not converted
        try:
            [float(token) for token in tokens[:count + 1]]
        except ValueError:
            raise InputError(f"calibration: key '{key}' in {path}: expected numbers, "
                             f"got {entries[key][:60]!r}") from None
        raise InputError(f"calibration: key '{key}' in {path}: expected {count} numbers {shape}, got {len(tokens)}")
    try:
        values = np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError:
        raise InputError(f"calibration: key '{key}' in {path}: expected numbers, "
                         f"got {entries[key][:60]!r}") from None
    return values.reshape(shape)


# --------------------------------------------------------------------------- YAML and JSON


class _Refused(Exception):
    """A document refused while it is parsed: the message after ``<what>: ``, ``{path}`` standing for the file."""


class _YamlLoader(_YAML_BASE):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML keeps the last silently).

    Run on a document :func:`_check_yaml_events` has passed: no anchors or aliases, at most
    ``MAX_YAML_DEPTH`` levels and ``MAX_YAML_NODES`` nodes.
    """

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:  # unhashable: PyYAML's own error follows
                    continue
                line = key_node.start_mark.line + 1
                if first is not None:
                    raise _Refused(f"expected each key once in {{path}}, got {quote_key(key)} twice (lines {first} "
                                   f"and {line}): which value is meant cannot be told")
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def _check_yaml_events(text: str) -> None:
    """Refuse, from the parser's events and before any node is built: anchors and aliases (``&a``,
    ``*a``; a kilobyte of nested aliases expands to gigabytes), nesting deeper than ``MAX_YAML_DEPTH``
    and more than ``MAX_YAML_NODES`` nodes (stopping there: a 1 MiB list is not parsed whole)."""
    depth = nodes = 0
    for event in yaml.parse(text, Loader=_YAML_BASE):
        line = event.start_mark.line + 1
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
            kind = "an alias *" if isinstance(event, yaml.AliasEvent) else "an anchor &"
            raise _Refused(f"expected plain YAML without anchors or aliases (&name, *name) in {{path}}, got "
                           f"{kind}{str(event.anchor)[:40]} on line {line}")
        if isinstance(event, yaml.NodeEvent):
            nodes += 1
            if nodes > MAX_YAML_NODES:
                raise _Refused(f"expected a calibration of at most {MAX_YAML_NODES} YAML values in {{path}}, got "
                               f"more (line {line})")
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise _Refused(f"expected YAML nested at most {MAX_YAML_DEPTH} levels deep in {{path}}, got deeper "
                               f"nesting on line {line}")
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


def _json_pairs(pairs: list) -> dict:
    """``object_pairs_hook`` of the JSON reader: a key given twice is refused."""
    data = {}
    for key, value in pairs:
        if key in data:
            raise _Refused(f"expected each key once in {{path}}, got {quote_key(key)} twice: which value is meant "
                           f"cannot be told")
        data[key] = value
    return data


def read_mapping(text: str, path: Path, kind: str, what: str = "calibration") -> object:
    """The ``kind`` ("YAML" or "JSON") document ``text`` of the calibration file ``path``, every
    mapping's keys given once; YAML without anchors or aliases, at most ``MAX_YAML_DEPTH`` levels
    deep and of at most ``MAX_YAML_NODES`` values; else InputError naming ``what`` and ``path``."""
    try:
        if kind == "JSON":
            return json.loads(text, object_pairs_hook=_json_pairs)
        _check_yaml_events(text)
        loader = _YamlLoader(text)
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except _Refused as exc:
        raise InputError(f"{what}: {str(exc).replace('{path}', str(path))}") from None
    except RecursionError:
        raise InputError(f"{what}: expected {kind} nested a few levels deep (a rig needs 3) in {path}, got "
                         f"nesting too deep to parse") from None
    except (ValueError, yaml.YAMLError) as exc:  # ValueError: also an integer of over 4300 digits
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"{what}: {path} is not valid {kind}: {first[:200]}") from None


# A rig file's own keys at the top level of its YAML (``K:`` at the start of a line) or JSON (``"K":``); a KITTI
# calibration has neither (its keys: P0..P3, R0_rect, Tr_velo_to_cam, R, T, S_rect_0X, P_rect_0X, ...).
_RIG_KEY = re.compile(r'^(?:K|T_cam_lidar)\s*:|"(?:K|T_cam_lidar)"\s*:', re.MULTILINE)


def is_rig_file(path: str | Path) -> bool:
    """Is ``path`` a rig calibration (YAML / JSON with ``K`` or ``T_cam_lidar``) whatever its name says? A
    folder, a file that cannot be read and a KITTI calibration are not (their own readers tell what is wrong)."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        with open(path, "rb") as handle:
            head = handle.read(MAX_CALIBRATION_BYTES)
    except OSError:
        return False
    return _RIG_KEY.search(head.decode("utf-8", errors="replace")) is not None
