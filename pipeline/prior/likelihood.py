"""Likelihood tables r_i(F_i(x)) per feature, their product, and their TOML form.

TOML (``[likelihood.<feature>]`` tables, the same whether hand-set or learned)::

    [likelihood.water]
    type = "categorical"
    values = { dry = 1.0, water = 0.0 }     # keys: category labels (or codes as text); 0 = structural zero
    nodata = 1.0                            # optional: likelihood of no-data cells (default 1, neutral)

    [likelihood.road_distance]
    type = "road"                           # paper 1: (1-mv)·exp(-((d-rmd)/rmd)²/2) + mv
    rmd = 150.0                             # metres, > 0
    mv = 0.2                                # in (0, 1]

    [likelihood.slope_deg]
    type = "binned"                         # piecewise constant in a continuous feature
    edges = [0, 5, 15, 30]                  # left bin edges in the feature's units; last bin open
    values = [1.0, 0.8, 0.4, 0.1]
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numba as nb
import numpy as np
import tomli_w

from common.atomic import atomic_paths
from pipeline.features.stack import _DENSE_CODE_RANGE, Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE


class LikelihoodError(ValueError):
    """A likelihood table that does not fit its feature or is malformed."""


def read_toml(path: str | Path, what: str, error: type[ValueError]) -> dict:
    """Parse a TOML file; a missing or malformed file raises ``error`` naming the path and ``what`` it is."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, not a {what} (TOML file)") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a text TOML file (byte {exc.start} is not UTF-8); is it the {what}?") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None


def _number(key: str, v: object, positive: bool = False) -> float:
    """``v`` as a finite float >= 0 (> 0 if ``positive``); LikelihoodError naming ``key`` otherwise."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise LikelihoodError(f"{key} must be a number, got {v!r}")
    x = float(v)
    if not (math.isfinite(x) and (x > 0 if positive else x >= 0)):
        raise LikelihoodError(f"{key} must be {'> 0' if positive else '>= 0'} and finite, got {x}")
    return x


def _numbers(key: str, v: object, positive: bool = False) -> list[float]:
    """A non-empty list of numbers checked by :func:`_number` (keys ``key[i]``)."""
    if not isinstance(v, list | tuple) or not v:
        raise LikelihoodError(f"{key} must be a non-empty list of numbers, got {v!r}")
    return [_number(f"{key}[{i}]", x, positive) for i, x in enumerate(v)]


class Likelihood(Protocol):
    def __call__(self, feature: Feature) -> np.ndarray:
        """r_i(F_i(x)) on the feature's grid (float64, >= 0)."""

    def to_dict(self) -> dict: ...


@dataclass
class CategoricalLikelihood:
    """Likelihood per category label; 0 marks a structural zero (e.g. water)."""

    values: dict[str, float]
    nodata: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.values, Mapping) or not self.values:
            raise LikelihoodError(f"values must be a table {{ label = likelihood, ... }}, got {self.values!r}")
        self.values = {str(k): _number(f"values.{k}", v) for k, v in self.values.items()}
        self.nodata = _number("nodata", self.nodata)

    def __call__(self, feature: Feature) -> np.ndarray:
        if feature.kind != "categorical":
            raise LikelihoodError(f"feature {feature.name!r} is {feature.kind}, a categorical table needs categories")
        codes = feature.codes()
        values = np.empty(codes.shape[0], dtype=np.float64)
        for k, code in enumerate(codes):
            label = feature.label(code)
            value = self.values.get(label, self.values.get(str(int(code))))
            if value is None:
                raise LikelihoodError(
                    f"feature {feature.name!r}: category {label!r} (code {int(code)}) has no likelihood; "
                    f"table has {sorted(self.values)}"
                )
            values[k] = value
        lo = min(NODATA_CODE, int(codes[0])) if codes.size else NODATA_CODE
        hi = int(codes[-1]) if codes.size else NODATA_CODE
        if hi - lo < _DENSE_CODE_RANGE:
            # Dense look-up by code offset: one gather instead of a search per cell.
            lut = np.full(hi - lo + 1, self.nodata)
            lut[codes - lo] = values
            out = np.empty(feature.values.shape)
            _gather(feature.values.reshape(-1), lut, lo, out.reshape(-1))
            return out
        lut_codes = np.append(codes, NODATA_CODE)
        lut_vals = np.append(values, self.nodata)
        order = np.argsort(lut_codes)
        return lut_vals[order][np.searchsorted(lut_codes[order], feature.values)]

    def to_dict(self) -> dict:
        return {"type": "categorical", "values": dict(self.values), "nodata": self.nodata}


@nb.njit(cache=True)
def _gather(codes: np.ndarray, lut: np.ndarray, lo: int, out: np.ndarray) -> None:
    """out[i] = lut[codes[i] - lo]: a look-up without the index temporaries of numpy's fancy indexing."""
    for i in range(codes.shape[0]):
        out[i] = lut[codes[i] - lo]


def road_likelihood(d: np.ndarray, rmd: float, mv: float) -> np.ndarray:
    """Paper 1's road-distance form (1-mv)·exp(-((d-rmd)/rmd)²/2) + mv, d in metres."""
    z = np.array(d, dtype=np.float64)
    # (-0.5·z)·z and the rest in the formula's order, in two arrays instead of seven temporaries
    z -= rmd
    z /= rmd
    w = -0.5 * z
    w *= z
    np.exp(w, out=w)
    w *= 1.0 - mv
    w += mv
    return w


@dataclass
class RoadDistanceLikelihood:
    """Paper 1's road-distance likelihood; ``rmd`` metres (> 0), ``mv`` in (0, 1]."""

    rmd: float
    mv: float
    nodata: float = 1.0

    def __post_init__(self) -> None:
        self.rmd = _number("rmd", self.rmd, positive=True)
        self.mv = _number("mv", self.mv, positive=True)
        if self.mv > 1:
            raise LikelihoodError(f"mv must be in (0, 1], got {self.mv}")
        self.nodata = _number("nodata", self.nodata)

    def __call__(self, feature: Feature) -> np.ndarray:
        if feature.kind != "continuous":
            raise LikelihoodError(f"feature {feature.name!r} must be a continuous distance in metres")
        out = road_likelihood(feature.values, self.rmd, self.mv)
        out[np.isnan(feature.values)] = self.nodata
        return out

    def to_dict(self) -> dict:
        return {"type": "road", "rmd": self.rmd, "mv": self.mv, "nodata": self.nodata}


@dataclass
class BinnedLikelihood:
    """Piecewise-constant likelihood of a continuous feature; ``edges`` are left bin edges (ascending)."""

    edges: list[float]
    values: list[float]
    nodata: float = 1.0

    def __post_init__(self) -> None:
        if not (isinstance(self.edges, list | tuple) and self.edges and all(
                isinstance(e, numbers.Real) and not isinstance(e, bool) and math.isfinite(e) for e in self.edges)):
            raise LikelihoodError(f"edges must be a non-empty list of finite numbers (left bin edges), got {self.edges!r}")
        self.edges = [float(e) for e in self.edges]
        self.values = _numbers("values", self.values)
        if len(self.edges) != len(self.values):
            raise LikelihoodError(f"edges and values must be as many, got {len(self.edges)} edges and {len(self.values)} values")
        if np.any(np.diff(self.edges) <= 0):
            raise LikelihoodError(f"edges must increase, got {self.edges}")
        self.nodata = _number("nodata", self.nodata)

    def __call__(self, feature: Feature) -> np.ndarray:
        if feature.kind != "continuous":
            raise LikelihoodError(f"feature {feature.name!r} must be continuous for a binned table")
        x = feature.values.astype(np.float64)
        idx = np.clip(np.searchsorted(self.edges, x, side="right") - 1, 0, len(self.edges) - 1)
        out = np.asarray(self.values, dtype=np.float64)[idx]
        out[np.isnan(x)] = self.nodata
        return out

    def to_dict(self) -> dict:
        return {"type": "binned", "edges": list(self.edges), "values": list(self.values), "nodata": self.nodata}


_TYPES = {"categorical": CategoricalLikelihood, "road": RoadDistanceLikelihood, "binned": BinnedLikelihood}


def likelihood_from_dict(name: str, d: object, source: str = "config") -> Likelihood:
    """Build one feature's likelihood from its TOML table; errors name ``source``, the table and the key."""
    where = f"{source}: [likelihood.{name}]"
    if not isinstance(d, Mapping):
        raise LikelihoodError(f"{where}: must be a table (type = ..., ...), got {d!r}")
    d = dict(d)
    kind = d.pop("type", None)
    if kind not in _TYPES:
        raise LikelihoodError(f"{where}: type must be one of {sorted(_TYPES)}, got {kind!r}")
    keys = {f.name: f.default is dataclasses.MISSING for f in dataclasses.fields(_TYPES[kind])}
    unknown = sorted(set(d) - set(keys))
    if unknown:
        raise LikelihoodError(f"{where}: unknown keys {unknown}; a {kind} table has {sorted(keys)}")
    missing = sorted(k for k, required in keys.items() if required and k not in d)
    if missing:
        raise LikelihoodError(f"{where}: {missing[0]} is missing")
    try:
        return _TYPES[kind](**d)
    except LikelihoodError as exc:  # the table's own check, naming the key
        raise LikelihoodError(f"{where}: {exc}") from None


@dataclass
class LikelihoodModel:
    """The product r(x) = Π_i r_i(F_i(x)) over named feature likelihoods."""

    terms: dict[str, Likelihood] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def evaluate(self, stack: FeatureStack) -> np.ndarray:
        """Unnormalised r on the stack's grid."""
        r = None  # the first factor itself: 1 · x is x, so the product is the same to the bit
        for name, term in self.terms.items():
            if name not in stack:
                raise LikelihoodError(f"[likelihood.{name}]: no such feature; features: {sorted(stack.features)}")
            try:
                factor = term(stack[name])
            except LikelihoodError as exc:  # a table that does not fit its feature: name the table
                raise LikelihoodError(f"[likelihood.{name}]: {exc}") from None
            if r is None:
                r = np.array(factor, dtype=np.float64)  # a copy: a term may return an array it keeps
            else:
                r *= factor
        return np.ones(stack.grid.shape) if r is None else r

    def to_dict(self) -> dict:
        out: dict = {"likelihood": {n: t.to_dict() for n, t in self.terms.items()}}
        if self.meta:
            out["meta"] = self.meta
        return out

    @classmethod
    def from_dict(cls, d: dict, source: str = "config") -> LikelihoodModel:
        tables = d.get("likelihood")
        if not isinstance(tables, dict) or not tables:
            raise LikelihoodError(f"{source}: no [likelihood.<feature>] tables")
        meta = d.get("meta", {})
        if not isinstance(meta, dict):
            raise LikelihoodError(f"{source}: [meta] must be a table, got {meta!r}")
        return cls({n: likelihood_from_dict(n, t, source) for n, t in tables.items()}, dict(meta))

    def write_toml(self, path: str | Path) -> Path:
        with atomic_paths(path) as (tmp,):
            tmp.write_bytes(tomli_w.dumps(self.to_dict()).encode())
        return Path(path)

    @classmethod
    def read_toml(cls, path: str | Path) -> LikelihoodModel:
        return cls.from_dict(read_toml(path, "likelihood file", LikelihoodError), str(path))
