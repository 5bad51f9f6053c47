"""The ``[learn]`` table of a region config: how ``terrain-prior learn`` fits and evaluates.

::

    [learn]
    features = ["water", "slope_class", "road_distance", "protected"]  # default: the [likelihood] tables
    on_zero = "drop"            # points on structural zeros: "drop" (counted) or "soften"
    soften = 0.001              # likelihood given to structural zeros when softened
    penalty_sd = 3.0            # Gaussian prior sd on each log-likelihood (nats)
    smooth_sd = 1.0             # ... on differences of adjacent bins of a binned term
    bin_width = 5.0             # fine bins of distances (metres; default a quarter cell)
    flexible = { road_distance = [0, 25, 50, 100, 200, 400, 800, 1600] }   # bins instead of the road form
    folds = 5                   # spatial block cross-validation
    block_size_m = 2000.0
    bandwidths_m = [40, 80, 160, 320, 640]   # KDE candidates (default: 2 cells .. 1/5 of the grid)
    hybrid = true               # also fit and evaluate terrain × (α + (1-α)·KDE/uniform)^γ
    defensive = "cv"            # p = (1-ε)·p_model + ε·uniform: ε by cross-fitted ML ("cv"), a number, or "none"
    temper = "cv"               # p ∝ r^τ before the mixture: τ by the same cross-fitted ML, a number, or "none" (default)
    weights = "count"           # a column of the targets giving each point's weight (--weights overrides)
    clamp = true                # continuous forms held at their end value beyond the training points' range
    select = "backward"         # drop features by backward elimination on spatial block CV (default "none")

    [learn.mixture.towns]           # optional: a mixture of priors, one per table (at least 2), its
    features = ["water", "road_distance", "residential_distance"]   # weights chosen on cross-fitted blocks
    [learn.mixture.farmland]
    features = ["water", "road_distance", "waterbody_distance"]

    [learn.forms.road_distance]     # a feature's form (overrides its [likelihood] table's)
    form = "decreasing"             # categorical | road | bins | linear | increasing | decreasing | spline
    scale = "log1p"                 # g(v) the form is in: "linear" (v) or "log1p" (log(1 + v))
    knots = 8                       # knot intervals (monotone: hinges; spline: B-spline intervals)
    # smoothing = 10.0              # spline: fixed λ (default: chosen by AIC)
    # edges = [0, 50, 200]          # bins: left edges

The region's ``[likelihood.*]`` tables are the template: forms, bin edges, structural zeros (0),
start values. The table is read here and removed before the region config is validated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.config.region import ConfigError, RegionConfig, parse_config
from pipeline.prior.likelihood import read_toml

_KEYS = {
    "features", "on_zero", "soften", "penalty_sd", "smooth_sd", "bin_width", "flexible",
    "folds", "block_size_m", "bandwidths_m", "hybrid", "forms", "defensive", "temper", "weights",
    "clamp", "mixture", "select",
}
FORMS = ("categorical", "road", "bins", "linear", "increasing", "decreasing", "spline")
_FORM_KEYS = {"form", "scale", "knots", "smoothing", "bins", "edges"}


@dataclass(frozen=True)
class FormSpec:
    """How one feature is fitted (see docs/learn.md, "Forms"): ``form`` one of :data:`FORMS`;
    basis forms (linear, increasing, decreasing, spline) in ``scale`` ("linear" or "log1p") with
    ``knots`` knot intervals (default 8 for monotone forms, 10 for the spline), ``smoothing`` the
    spline's fixed λ (None: chosen by AIC) and ``bins`` fine bins of the sufficient statistics;
    ``edges`` the left bin edges of the bins form. ValueError names the bad key."""

    form: str
    scale: str = "linear"
    knots: int | None = None
    smoothing: float | None = None
    bins: int = 100
    edges: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.form not in FORMS:
            raise ValueError(f"form: must be one of {list(FORMS)}, got {self.form!r}")
        if self.scale not in ("linear", "log1p"):
            raise ValueError(f"scale: must be \"linear\" or \"log1p\", got {self.scale!r}")
        if self.knots is not None and not (isinstance(self.knots, int) and not isinstance(self.knots, bool) and 1 <= self.knots <= 100):
            raise ValueError(f"knots: must be an integer in 1..100, got {self.knots!r}")
        if self.form == "spline" and self.knots is not None and self.knots < 2:
            raise ValueError(f"knots: a spline needs at least 2 knot intervals, got {self.knots}")
        if self.smoothing is not None and not (isinstance(self.smoothing, int | float) and not isinstance(self.smoothing, bool)
                                               and math.isfinite(self.smoothing) and self.smoothing >= 0):
            raise ValueError(f"smoothing: must be a non-negative number (the spline's λ), got {self.smoothing!r}")
        if not (isinstance(self.bins, int) and not isinstance(self.bins, bool) and 8 <= self.bins <= 100_000):
            raise ValueError(f"bins: must be an integer in 8..100000, got {self.bins!r}")
        if self.form == "bins":
            e = self.edges
            if not (isinstance(e, list | tuple) and e and all(isinstance(v, int | float) and not isinstance(v, bool) for v in e)):
                raise ValueError(f"edges: the bins form needs a list of left bin edges, got {e!r}")
            if any(b <= a for a, b in zip(e, e[1:], strict=False)):
                raise ValueError(f"edges: must increase, got {list(e)}")
            object.__setattr__(self, "edges", tuple(float(v) for v in e))
        elif self.edges is not None:
            raise ValueError(f"edges: only the bins form takes edges (form is {self.form!r})")
        if self.knots is None and self.form in ("increasing", "decreasing", "spline"):
            object.__setattr__(self, "knots", 10 if self.form == "spline" else 8)


@dataclass(frozen=True)
class LearnConfig:
    """Validated ``[learn]`` settings (defaults as in :class:`pipeline.learn.estimator.PriorEstimator`)."""

    features: tuple[str, ...] | None = None
    on_zero: str = "drop"
    soften: float = 1e-3
    penalty_sd: float = 3.0
    smooth_sd: float = 1.0
    bin_width: float | None = None
    flexible: dict[str, list[float]] = field(default_factory=dict)
    folds: int = 5
    block_size_m: float = 2000.0
    bandwidths_m: tuple[float, ...] | None = None
    hybrid: bool = True
    forms: dict[str, FormSpec] = field(default_factory=dict)
    defensive: float | str | None = "cv"
    temper: float | str | None = None
    weights: str | None = None
    clamp: bool = True
    mixture: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Components of a mixture prior (name -> its features); empty: no mixture."""
    select: str | None = None
    """"backward": choose the features by backward elimination on spatial block CV
    (:class:`pipeline.learn.select.BackwardSelection`); None: fit the features as listed."""


def _positive(source: Path, key: str, v: object, allow_zero: bool = False) -> float:
    ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
    if not ok:
        raise ConfigError(f"{source}: learn.{key}: must be a {'non-negative' if allow_zero else 'positive'} number, got {v!r}")
    return float(v)


def parse_learn(d: dict, source: Path) -> LearnConfig:
    """Validate a ``[learn]`` table."""
    if not isinstance(d, dict):
        raise ConfigError(f"{source}: [learn] must be a table")
    unknown = sorted(set(d) - _KEYS)
    if unknown:
        raise ConfigError(f"{source}: [learn]: unknown keys {unknown}; allowed {sorted(_KEYS)}")
    kw: dict = {}
    if "features" in d:
        f = d["features"]
        if not (isinstance(f, list) and f and all(isinstance(s, str) for s in f)):
            raise ConfigError(f"{source}: learn.features: expected a list of feature names, got {f!r}")
        kw["features"] = tuple(f)
    if "on_zero" in d:
        if d["on_zero"] not in ("drop", "soften"):
            raise ConfigError(f"{source}: learn.on_zero: must be \"drop\" or \"soften\", got {d['on_zero']!r}")
        kw["on_zero"] = d["on_zero"]
    for key in ("soften", "penalty_sd", "block_size_m", "bin_width"):
        if key in d:
            kw[key] = _positive(source, key, d[key])
    if "soften" in kw and not kw["soften"] < 1:
        raise ConfigError(f"{source}: learn.soften: must be in (0, 1), got {kw['soften']}")
    if "smooth_sd" in d:
        kw["smooth_sd"] = _positive(source, "smooth_sd", d["smooth_sd"], allow_zero=True)
    if "folds" in d:
        if not (isinstance(d["folds"], int) and not isinstance(d["folds"], bool) and d["folds"] >= 2):
            raise ConfigError(f"{source}: learn.folds: must be an integer >= 2, got {d['folds']!r}")
        kw["folds"] = d["folds"]
    if "bandwidths_m" in d:
        b = d["bandwidths_m"]
        if not isinstance(b, list) or not b:
            raise ConfigError(f"{source}: learn.bandwidths_m: expected a list of metres, got {b!r}")
        kw["bandwidths_m"] = tuple(_positive(source, "bandwidths_m", v) for v in b)
    if "hybrid" in d:
        if not isinstance(d["hybrid"], bool):
            raise ConfigError(f"{source}: learn.hybrid: must be true or false, got {d['hybrid']!r}")
        kw["hybrid"] = d["hybrid"]
    if "flexible" in d:
        fl = d["flexible"]
        if not isinstance(fl, dict):
            raise ConfigError(f"{source}: learn.flexible: expected a table feature = [left bin edges], got {fl!r}")
        out = {}
        for name, edges in fl.items():
            if not (isinstance(edges, list) and edges and all(isinstance(e, int | float) and not isinstance(e, bool) for e in edges)):
                raise ConfigError(f"{source}: learn.flexible.{name}: expected a list of numbers, got {edges!r}")
            if any(b <= a for a, b in zip(edges, edges[1:], strict=False)):
                raise ConfigError(f"{source}: learn.flexible.{name}: edges must increase, got {edges}")
            out[name] = [float(e) for e in edges]
        kw["flexible"] = out
    if "forms" in d:
        if not isinstance(d["forms"], dict):
            raise ConfigError(f"{source}: learn.forms: expected tables [learn.forms.<feature>], got {d['forms']!r}")
        forms = {}
        for name, spec in d["forms"].items():
            if not isinstance(spec, dict):
                raise ConfigError(f"{source}: learn.forms.{name}: expected a table with form = ..., got {spec!r}")
            unknown = sorted(set(spec) - _FORM_KEYS)
            if unknown or "form" not in spec:
                raise ConfigError(f"{source}: learn.forms.{name}: " + (f"unknown keys {unknown}; allowed {sorted(_FORM_KEYS)}"
                                                                      if unknown else "no form = ... key"))
            try:
                forms[name] = FormSpec(**spec)
            except ValueError as e:
                raise ConfigError(f"{source}: learn.forms.{name}.{e}") from None
        kw["forms"] = forms
    if "defensive" in d:
        v = d["defensive"]
        if v == "none":
            kw["defensive"] = None
        elif v == "cv":
            kw["defensive"] = "cv"
        elif isinstance(v, int | float) and not isinstance(v, bool) and 0 <= v < 1:
            kw["defensive"] = float(v)
        else:
            raise ConfigError(f"{source}: learn.defensive: must be \"cv\", \"none\" or a number in [0, 1), got {v!r}")
    if "temper" in d:
        v = d["temper"]
        if v in ("none", "cv"):
            kw["temper"] = None if v == "none" else "cv"
        elif isinstance(v, int | float) and not isinstance(v, bool) and 0.05 <= v <= 1.5:
            kw["temper"] = float(v)
        else:
            raise ConfigError(f"{source}: learn.temper: must be \"cv\", \"none\" or a number in [0.05, 1.5], got {v!r}")
    if "weights" in d:
        if not (isinstance(d["weights"], str) and d["weights"]):
            raise ConfigError(f"{source}: learn.weights: expected a column name of the targets, got {d['weights']!r}")
        kw["weights"] = d["weights"]
    if "clamp" in d:
        if not isinstance(d["clamp"], bool):
            raise ConfigError(f"{source}: learn.clamp: must be true or false, got {d['clamp']!r}")
        kw["clamp"] = d["clamp"]
    if "mixture" in d:
        kw["mixture"] = _mixture(d["mixture"], source)
    if "select" in d:
        if d["select"] not in ("backward", "none"):
            raise ConfigError(f"{source}: learn.select: must be \"backward\" or \"none\", got {d['select']!r}")
        kw["select"] = None if d["select"] == "none" else "backward"
    return LearnConfig(**kw)


def _mixture(m: object, source: Path) -> dict[str, tuple[str, ...]]:
    """``[learn.mixture.<name>] features = [...]`` tables: at least two components."""
    if not isinstance(m, dict) or len(m) < 2:
        raise ConfigError(f"{source}: learn.mixture: expected at least 2 tables [learn.mixture.<name>] features = [...], got {m!r}")
    out = {}
    for name, spec in m.items():
        if not isinstance(spec, dict) or set(spec) != {"features"}:
            raise ConfigError(f"{source}: learn.mixture.{name}: expected a table with only features = [...], got {spec!r}")
        f = spec["features"]
        if not (isinstance(f, list) and f and all(isinstance(v, str) for v in f)):
            raise ConfigError(f"{source}: learn.mixture.{name}.features: expected a list of feature names, got {f!r}")
        out[name] = tuple(f)
    return out


def load_learn_config(path: str | Path) -> tuple[RegionConfig, LearnConfig]:
    """The region config and its ``[learn]`` table (defaults when absent)."""
    path = Path(path).resolve()
    d = read_toml(path, "region config", ConfigError)
    learn = parse_learn(d.pop("learn", {}), path)
    region = parse_config(d, path)
    if learn.features:
        missing = [f for f in learn.features if f not in region.features]
        if missing:
            raise ConfigError(f"{path}: learn.features: no feature {missing[0]!r}; features are {sorted(region.features)}")
    for name, features in learn.mixture.items():
        missing = [f for f in features if f not in region.features]
        if missing:
            raise ConfigError(f"{path}: learn.mixture.{name}.features: no feature {missing[0]!r}; features are {sorted(region.features)}")
    for key, names in (("flexible", learn.flexible), ("forms", learn.forms)):
        for name in names:
            if name not in region.features:
                raise ConfigError(f"{path}: learn.{key}: no feature {name!r}; features are {sorted(region.features)}")
    return region, learn
