"""Tracker configurations as versioned JSON: :func:`config_to_dict` / :func:`config_from_dict`
and the files :func:`save_config` writes and :func:`load_config` reads (``phjax tune -o``,
the CLI's ``--config``). Re-exported by :mod:`phjax.tracking.tuning`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from .imm import IMMConfig
from .kalman import KalmanConfig
from .models import ConstantAcceleration, ConstantVelocity
from .tracker import TrackerConfig

#: ``"format"`` tag and version of the JSON written by :func:`save_config`.
CONFIG_FORMAT = "phjax.TrackerConfig"
CONFIG_VERSION = 1


def _jsonable(v):
    if v is None or isinstance(v, (bool, int, str)):
        return v
    a = np.asarray(v)
    if a.ndim == 0:
        return a.item()
    return a.tolist()


def _field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def config_to_dict(config: TrackerConfig, metadata: dict | None = None) -> dict:
    """JSON-ready dict of every :class:`~phjax.TrackerConfig` and :class:`~phjax.KalmanConfig`
    field (format tag, version, ``"tracker"`` and ``"kalman"`` sections, optional
    ``"metadata"``)."""
    tracker = {n: _jsonable(getattr(config, n))
               for n in _field_names(TrackerConfig) if n not in ("kalman", "imm")}
    kalman = {n: _jsonable(getattr(config.kalman, n)) for n in _field_names(KalmanConfig)}
    out = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, "tracker": tracker, "kalman": kalman,
           "imm": _imm_to_dict(config.imm)}
    if metadata:
        out["metadata"] = json.loads(json.dumps(metadata, default=_jsonable))
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


def _imm_from_dict(sec, source: str) -> IMMConfig | None:
    if sec is None:
        return None
    if not isinstance(sec, dict):
        raise ValueError(f"{source}: 'imm' must be an object or null")
    sec = dict(sec)
    try:
        kw = {}
        for key in ("position_models", "rotation_models"):
            if key in sec:
                kw[key] = tuple(_MODEL_KINDS[m["model"]](log_q=float(m["log_q"]))
                                for m in sec.pop(key))
        for name, value in sec.items():  # numbers only (true is not 1.0)
            if isinstance(value, bool):
                raise ValueError(f"imm.{name} has an invalid value {value!r}")
        return IMMConfig(**kw, **sec)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid imm section: {err}") from err


def config_from_dict(d: dict, source: str = "<dict>") -> TrackerConfig:
    """Inverse of :func:`config_to_dict` (missing fields take their defaults; a missing ``"imm"``
    section means the single-model filter, as in files written before the IMM existed).

    Raises:
        ValueError: wrong format tag or version, unknown sections or fields, bad values.
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
            scalar = value is None or isinstance(value, (int, float, str))
            # true / false only for the switches (a number field given true is a mistake)
            if isinstance(value, bool) != (name in flags) or not scalar:
                raise ValueError(f"{source}: {key}.{name} has an invalid value {value!r}")
        sections[key] = sec
    try:
        kalman = KalmanConfig(**sections["kalman"])
        # no "imm" section: a file from before the IMM, i.e. the single-model stream
        imm = _imm_from_dict(d.get("imm"), source)
        return TrackerConfig(kalman=kalman, imm=imm, **sections["tracker"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid configuration: {err}") from err


def save_config(
    path: str | os.PathLike, config: TrackerConfig, metadata: dict | None = None
) -> Path:
    """Write ``config`` (all fields, versioned) as JSON; ``metadata`` is stored alongside.

    Returns:
        The path written.
    """
    path = Path(path)
    path.write_text(json.dumps(config_to_dict(config, metadata), indent=2) + "\n", encoding="utf-8")
    return path


def load_config(path: str | os.PathLike) -> TrackerConfig:
    """Read a configuration written by :func:`save_config` (or ``phjax tune``).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not valid JSON, wrong format/version, unknown fields or bad values.
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a JSON text file (byte {err.start} is not UTF-8)"
                         ) from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err
    return config_from_dict(d, str(path))
