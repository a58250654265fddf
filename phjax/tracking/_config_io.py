"""Tracker configurations as versioned JSON: :func:`config_to_dict` / :func:`config_from_dict`
and the files :func:`save_config` writes and :func:`load_config` reads (``phjax tune -o``,
the CLI's ``--config``). Re-exported by :mod:`phjax.tracking.tuning`.

Reading is strict: a file is UTF-8 JSON (a leading byte-order mark is allowed) without
duplicate keys, each field holds a JSON value of its type (numbers for the float fields, not
``true`` or strings), and the float fields must lie in :data:`CONFIG_RANGES`, beyond which the
float32 stream overflows or underflows to NaN poses (a value inside them may still be a bad
choice; it is a finite one). :func:`save_config` writes only configurations that
:func:`load_config` reads back, and replaces an existing file atomically.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from .imm import IMMConfig
from .kalman import KalmanConfig
from .models import ConstantAcceleration, ConstantVelocity
from ._config_ranges import CONFIG_RANGES, out_of_range, range_message  # noqa: F401 (re-exported)
from .tracker import TrackerConfig

#: ``"format"`` tag and version of the JSON written by :func:`save_config`.
CONFIG_FORMAT = "phjax.TrackerConfig"
CONFIG_VERSION = 1

#: fields of a configuration file that hold a string (all others hold numbers, true / false
#: or null)
_STRING_FIELDS = {"kalman.model"}


def _jsonable(v):
    if v is None or isinstance(v, (bool, int, str)):
        return v
    a = np.asarray(v)
    if a.ndim == 0:
        return a.item()
    return a.tolist()


def _field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def _finite_or_null(v):
    """``v`` (parsed JSON) with every NaN / inf number replaced by ``None``."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _finite_or_null(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_finite_or_null(x) for x in v]
    return v


def config_to_dict(config: TrackerConfig, metadata: dict | None = None) -> dict:
    """JSON-ready dict of every :class:`~phjax.TrackerConfig` and :class:`~phjax.KalmanConfig`
    field (format tag, version, ``"tracker"`` and ``"kalman"`` sections, optional
    ``"metadata"``). Numbers in ``metadata`` that are NaN or infinite (a loss that could not
    be computed, an RMSE without data) become ``None`` (JSON ``null``): standard JSON has no
    NaN, and other readers (``jq``, JavaScript, strict parsers) reject the ``NaN`` Python
    writes."""
    tracker = {n: _jsonable(getattr(config, n))
               for n in _field_names(TrackerConfig) if n not in ("kalman", "imm")}
    kalman = {n: _jsonable(getattr(config.kalman, n)) for n in _field_names(KalmanConfig)}
    out = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, "tracker": tracker, "kalman": kalman,
           "imm": _imm_to_dict(config.imm)}
    if metadata:
        out["metadata"] = _finite_or_null(json.loads(json.dumps(metadata, default=_jsonable)))
    return out


_MODEL_KINDS = {"cv": ConstantVelocity, "ca": ConstantAcceleration}


def _imm_to_dict(imm: IMMConfig | None) -> dict | None:
    """The IMM section: models as ``{"model": "cv" | "ca", "log_q": log density}`` and the
    other :class:`IMMConfig` fields; ``None`` for the single-model filter."""
    if imm is None:
        return None

    def models(ms):
        return [{"model": "cv" if isinstance(m, ConstantVelocity) else "ca",
                 "log_q": _jsonable(m.log_q)} for m in ms]

    rest = {n: _jsonable(getattr(imm, n)) for n in _field_names(IMMConfig)
            if n not in ("position_models", "rotation_models")}
    return {"position_models": models(imm.position_models),
            "rotation_models": models(imm.rotation_models), **rest}


def _is_number(value) -> bool:
    """A JSON number (``true`` / ``false`` are not 1 / 0)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _models_from_list(models, key: str, source: str) -> tuple:
    if not isinstance(models, list):
        raise ValueError(f"{source}: invalid imm section: imm.{key} must be a list of "
                         f'{{"model": "cv" | "ca", "log_q": number}} objects, got {models!r}')
    out = []
    for i, m in enumerate(models):
        where = f"imm.{key}[{i}]"
        if not isinstance(m, dict) or set(m) != {"model", "log_q"}:
            raise ValueError(f"{source}: invalid imm section: {where} must be an object with "
                             f'the keys "model" and "log_q" only, got {m!r}')
        if not isinstance(m["model"], str) or m["model"] not in _MODEL_KINDS:
            raise ValueError(f"{source}: invalid imm section: {where}.model must be one of "
                             f"{sorted(_MODEL_KINDS)}, got {m['model']!r}")
        if not _is_number(m["log_q"]):
            raise ValueError(f"{source}: invalid imm section: {where}.log_q has an invalid "
                             f"value {m['log_q']!r}")
        try:
            out.append(_MODEL_KINDS[m["model"]](log_q=float(m["log_q"])))
        except (TypeError, ValueError) as err:
            raise ValueError(f"{source}: invalid imm section: {where}: {err}") from None
    return tuple(out)


def _imm_from_dict(sec, source: str) -> IMMConfig | None:
    if sec is None:
        return None
    if not isinstance(sec, dict):
        raise ValueError(f"{source}: 'imm' must be an object or null")
    sec = dict(sec)
    known = _field_names(IMMConfig)
    unknown = set(sec) - set(known)
    if unknown:
        raise ValueError(f"{source}: invalid imm section: unknown imm field(s) "
                         f"{sorted(unknown)}; known: {known}")
    kw = {key: _models_from_list(sec.pop(key), key, source)
          for key in ("position_models", "rotation_models") if key in sec}
    for name, value in sec.items():  # numbers only (true is not 1.0, "1" is not 1.0)
        if not _is_number(value):
            raise ValueError(f"{source}: invalid imm section: imm.{name} has an invalid "
                             f"value {value!r}")
    try:
        return IMMConfig(**kw, **sec)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid imm section: {err}") from None


def config_from_dict(d: dict, source: str = "<dict>") -> TrackerConfig:
    """Inverse of :func:`config_to_dict` (missing fields take their defaults; a missing ``"imm"``
    section means the single-model filter, as in files written before the IMM existed).

    Raises:
        ValueError: wrong format tag or version, unknown sections or fields, bad values
            (wrong JSON types, or outside :data:`CONFIG_RANGES`).
    """
    if not isinstance(d, dict):
        raise ValueError(f"{source}: expected a JSON object, got {type(d).__name__}")
    if d.get("format") != CONFIG_FORMAT:
        raise ValueError(f"{source}: not a phjax tracker configuration (format "
                         f"{d.get('format')!r}, expected {CONFIG_FORMAT!r})")
    version = d.get("version")
    if version != CONFIG_VERSION:
        raise ValueError(f"{source}: unsupported configuration version {version!r} "
                         f"(this phjax reads version {CONFIG_VERSION})")
    extra = set(d) - {"format", "version", "tracker", "kalman", "imm", "metadata"}
    if extra:
        raise ValueError(f"{source}: unknown top-level key(s) {sorted(extra)}")
    sections = {}
    for key, cls, skip in (("tracker", TrackerConfig, {"kalman", "imm"}),
                           ("kalman", KalmanConfig, set())):
        sec = d.get(key, {})
        if not isinstance(sec, dict):
            raise ValueError(f"{source}: '{key}' must be an object")
        known = [n for n in _field_names(cls) if n not in skip]
        unknown = set(sec) - set(known)
        if unknown:
            raise ValueError(f"{source}: unknown {key} field(s) {sorted(unknown)}; known: {known}")
        flags = {f.name for f in dataclasses.fields(cls) if isinstance(f.default, bool)}
        for name, value in sec.items():
            scalar = value is None or isinstance(value, (int, float)) or (
                isinstance(value, str) and f"{key}.{name}" in _STRING_FIELDS)
            # true / false only for the switches (a number field given true is a mistake)
            if isinstance(value, bool) != (name in flags) or not scalar:
                raise ValueError(f"{source}: {key}.{name} has an invalid value {value!r}")
        sections[key] = sec
    try:
        kalman = KalmanConfig(**sections["kalman"])
        config = TrackerConfig(kalman=kalman, imm=None, **sections["tracker"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid configuration: {err}") from None
    # no "imm" section: a file from before the IMM, i.e. the single-model stream
    imm = _imm_from_dict(d.get("imm"), source)
    config = config if imm is None else dataclasses.replace(config, imm=imm)
    bad = out_of_range(config)  # the ranges of configurations built in Python too
    if bad:
        raise ValueError(f"{source}: {range_message(*bad[0])}")
    return config


def save_config(
    path: str | os.PathLike, config: TrackerConfig, metadata: dict | None = None
) -> Path:
    """Write ``config`` (all fields, versioned) as JSON; ``metadata`` is stored alongside.

    The file is written to a temporary file beside ``path`` and then renamed over it, so an
    existing file is either kept or replaced whole, never left half written.

    Returns:
        The path written.

    Raises:
        TypeError: ``config`` is not a :class:`~phjax.TrackerConfig`, or ``metadata`` holds a
            value JSON cannot store.
        ValueError: a value :func:`load_config` would reject (see :data:`CONFIG_RANGES`).
        OSError: the file cannot be written (e.g. its folder does not exist).
    """
    if not isinstance(config, TrackerConfig):
        raise TypeError(f"save_config: config must be a phjax.TrackerConfig, got "
                        f"{type(config).__name__}")
    path = Path(path)
    if metadata is not None and not isinstance(metadata, dict):
        raise TypeError(f"{path}: metadata must be a dict, got {type(metadata).__name__}")
    try:
        d = config_to_dict(config, metadata)
    except (TypeError, ValueError) as err:  # json's "Circular reference" for an object
        raise TypeError(f"{path}: metadata is not JSON-serialisable ({err})") from None
    config_from_dict(d, str(path))  # never write a file that load_config rejects
    text = json.dumps(d, indent=2) + "\n"  # (an infinite gate is written as Infinity)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _no_duplicates(pairs: list) -> dict:
    keys = [k for k, _ in pairs]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise ValueError(f"duplicate key(s) {dup}")
    return dict(pairs)


def load_config(path: str | os.PathLike) -> TrackerConfig:
    """Read a configuration written by :func:`save_config` (or ``phjax tune``).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not valid JSON (also: duplicate keys, nesting too deep to read), wrong
            format/version, unknown fields or bad values (also: outside
            :data:`CONFIG_RANGES`).
        OSError: another unreadable path (e.g. a folder).
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8-sig"), object_pairs_hook=_no_duplicates)
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a JSON text file (byte {err.start} is not UTF-8)"
                         ) from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err
    except RecursionError:
        raise ValueError(f"{path}: not a tracker configuration (JSON nested too deeply)") from None
    except ValueError as err:  # _no_duplicates
        raise ValueError(f"{path}: not a valid configuration: {err}") from None
    return config_from_dict(d, str(path))
